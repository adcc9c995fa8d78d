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

# fixed colours so refined/live/raw look the same in every report
COLORS = {'ground truth': 'black', 'refined': 'tab:blue', 'estimate': 'tab:blue', 'raw': 'tab:orange',
          'live': 'tab:green'}
_CYCLE = ('tab:red', 'tab:purple', 'tab:brown', 'tab:pink', 'tab:olive', 'tab:cyan')


LIMIT = 1e300   # beyond (m, or cm on the error axis) matplotlib's axis limits overflow: drawn at +-LIMIT instead


def _drawable(values: np.ndarray) -> tuple[np.ndarray, bool]:
    """``values`` clipped to +-LIMIT (NaN left out of the line by matplotlib), and whether any was clipped."""
    values = np.asarray(values, dtype=float)
    with np.errstate(invalid='ignore'):
        clipped = bool(np.any(np.abs(values) > LIMIT))
    return np.clip(values, -LIMIT, LIMIT), clipped


def _cm(x: float | None) -> str:
    if x is None:
        return 'n/a'
    return f'{100 * x:{".1f" if abs(x) < 1e7 else ".2e"}} cm'


def _label(name: str, ev: Evaluation) -> str:
    """Legend entry; a measure the summary has no number for (beyond a float, e.g. positions of 1e300) is n/a."""
    pe = ev.summary['position_error_m']
    return f'{name} (mean {_cm(pe["mean"])}, terminal {_cm(pe["terminal"])})'


def plot_evaluation(path: str | os.PathLike, estimates: Mapping[str, Evaluation], *,
                    gt_stamps: np.ndarray | None = None, gt_xyz: np.ndarray | None = None,
                    title: str | None = None, dpi: int = 110) -> Path:
    """Write the PNG and return its path.

    ``estimates`` maps a label ('refined', 'raw', ...) to its :class:`Evaluation`; any may be left out.
    ``gt_xyz`` (full ground truth, (N, 3)) is drawn when given, else the associated ground truth of the
    first estimate. Axes follow base_link/odom (x forward, y left): x is drawn to the right, y up, with
    equal aspect so the path's shape is true. The error axis is time since the first stamp (the
    estimates may associate different frames), in cm. Absurd values (a diverged estimate) still give a figure:
    beyond +-:data:`LIMIT` they are drawn at the limit and the title says so.
    """
    if not estimates and gt_xyz is None:
        raise ValueError('nothing to plot: no estimate and no ground truth')
    fig = Figure(figsize=(12.0, 5.2))
    FigureCanvasAgg(fig)
    ax_xy, ax_err = fig.subplots(1, 2, gridspec_kw={'width_ratios': [1.0, 1.15]})

    first = next(iter(estimates.values()), None)
    gt = gt_xyz if gt_xyz is not None else (first.gt_xyz if first is not None else None)
    clipped = False
    if gt is not None and len(gt):
        gt, clipped = _drawable(gt)
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
        xyz, clip_xyz = _drawable(ev.est_xyz)
        with np.errstate(over='ignore'):
            err, clip_err = _drawable(100.0 * ev.position_error)
        clipped = clipped or clip_xyz or clip_err
        ax_xy.plot(xyz[:, 0], xyz[:, 1], color=color, lw=1.2, label=name, zorder=z)
        ax_xy.plot(xyz[-1, 0], xyz[-1, 1], 'x', color=color, ms=7, zorder=z)
        ax_err.plot(ev.stamps - t0, err, color=color, lw=1.2, label=_label(name, ev), zorder=z)

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

    if clipped:
        title = f'{title + ": " if title else ""}values beyond {LIMIT:g} drawn at {LIMIT:g}'
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi, format='png')
    return out
