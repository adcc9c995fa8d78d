"""Trajectory figure like the papers' Figs. 11-12: ground-plane path (left), position error per
step (right).

Uses matplotlib's object API on an Agg canvas (no pyplot, no display, no global backend switch), so
it is safe inside a node or a headless CI job.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from fixego_ros.evaluation.metrics import Evaluation

# fixed colours so refined/raw look the same in every report
COLORS = {'ground truth': 'black', 'refined': 'tab:blue', 'estimate': 'tab:blue', 'raw': 'tab:orange'}
_CYCLE = ('tab:green', 'tab:red', 'tab:purple', 'tab:brown', 'tab:pink', 'tab:olive', 'tab:cyan')


def _label(name: str, ev: Evaluation) -> str:
    pe = ev.summary['position_error_m']
    return f'{name} (mean {100 * pe["mean"]:.1f} cm, terminal {100 * pe["terminal"]:.1f} cm)'


def plot_evaluation(path: str | os.PathLike, estimates: Mapping[str, Evaluation], *,
                    gt_stamps: np.ndarray | None = None, gt_xyz: np.ndarray | None = None,
                    title: str | None = None, dpi: int = 110) -> Path:
    """Write the PNG and return its path.

    ``estimates`` maps a label ('refined', 'raw', ...) to its :class:`Evaluation`; any may be left out.
    ``gt_xyz`` (full ground truth, (N, 3)) is drawn when given, else the associated ground truth of the
    first estimate. Axes follow base_link/odom (x forward, y left): x is drawn to the right, y up, with
    equal aspect so the path's shape is true. The error axis is time since the first stamp (the
    estimates may associate different frames), in cm.
    """
    if not estimates and gt_xyz is None:
        raise ValueError('nothing to plot: no estimate and no ground truth')
    fig = Figure(figsize=(12.0, 5.2))
    FigureCanvasAgg(fig)
    ax_xy, ax_err = fig.subplots(1, 2, gridspec_kw={'width_ratios': [1.0, 1.15]})

    first = next(iter(estimates.values()), None)
    gt = gt_xyz if gt_xyz is not None else (first.gt_xyz if first is not None else None)
    if gt is not None and len(gt):
        gt = np.asarray(gt, dtype=float)
        ax_xy.plot(gt[:, 0], gt[:, 1], color=COLORS['ground truth'], lw=1.6, label='ground truth')
        ax_xy.plot(gt[0, 0], gt[0, 1], 'o', color='black', ms=5)

    starts = [float(ev.stamps[0]) for ev in estimates.values() if len(ev.stamps)]
    if gt_stamps is not None and len(gt_stamps):
        starts.append(float(gt_stamps[0]))
    t0 = min(starts) if starts else 0.0
    spare = iter(_CYCLE)
    for k, (name, ev) in enumerate(estimates.items()):
        color = COLORS.get(name) or next(spare, None)
        z = 3 + len(estimates) - k  # the first estimate (the refined one) on top
        ax_xy.plot(ev.est_xyz[:, 0], ev.est_xyz[:, 1], color=color, lw=1.2, label=name, zorder=z)
        ax_xy.plot(ev.est_xyz[-1, 0], ev.est_xyz[-1, 1], 'x', color=color, ms=7, zorder=z)
        ax_err.plot(ev.stamps - t0, 100.0 * ev.position_error, color=color, lw=1.2, label=_label(name, ev), zorder=z)

    ax_xy.set_aspect('equal', adjustable='datalim')
    ax_xy.set_xlabel('x (m, forward at start)')
    ax_xy.set_ylabel('y (m, left at start)')
    ax_xy.set_title('trajectory in odom (ground plane)')
    ax_xy.grid(True, alpha=0.3)
    ax_xy.legend(loc='best', fontsize=8)

    ax_err.set_xlabel('time since start (s)')
    ax_err.set_ylabel('position error (cm)')
    ax_err.set_title('position error per step (no alignment)')
    ax_err.set_ylim(bottom=0.0)
    ax_err.grid(True, alpha=0.3)
    if estimates:
        ax_err.legend(loc='upper left', fontsize=8)

    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi, format='png')
    return out
