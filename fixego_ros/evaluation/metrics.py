"""Error measures of an estimated trajectory against ground truth (DESIGN.md §5, §6).

Two families, because they answer different questions:

- the papers' measures, *without alignment*: both trajectories are poses of ``base_link`` in
  ``odom`` = the first frame, so the position error per frame, its mean/std and the terminal error
  show the drift a user of the live estimate would see (papers' Figs. 11-12);
- evo's APE (unaligned, SE(3)- and Sim(3)-aligned) and RPE (per frame, optionally per distance), the
  numbers other odometry work reports. Alignment and association are evo's, not re-implemented here.

:func:`evaluate` returns an :class:`Evaluation`: a JSON-ready ``summary`` dict and per-frame arrays
for plots.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from evo.core import metrics, sync
from evo.core.filters import FilterException
from evo.core.geometry import GeometryException
from evo.core.lie_algebra import LieAlgebraException
from evo.core.trajectory import PoseTrajectory3D

from fixego_ros.geometry.rotation import Pose

DEFAULT_MAX_DT = 0.01  # s; images at 30 Hz are 33 ms apart, so a 10 ms window never pairs the wrong frame
GROWTH_WINDOW_S = 4.0  # s; the stretch over which :func:`error_growth` looks for the error's largest rise
HEADING_BACK_M = 0.5   # m of the true path before the end that give the direction of travel there


class EvaluationError(ValueError):
    """The trajectories cannot be compared (too few associated poses, no common stamps)."""


@dataclass
class Evaluation:
    """Result of :func:`evaluate`. Arrays are per associated frame (length ``n``)."""

    summary: dict[str, Any]
    stamps: np.ndarray  # stamps of the estimate at the associated frames (s)
    est_xyz: np.ndarray  # (n, 3) estimated positions (base_link in odom, as compared)
    gt_xyz: np.ndarray  # (n, 3) true positions at the same frames
    position_error: np.ndarray  # (n,) unaligned position error (m), the papers' measure
    rpe_translation: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (n-1,) m per frame
    rpe_rotation_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (n-1,) deg per frame


def to_evo(stamps: Sequence[float] | np.ndarray, poses: Sequence[Pose], name: str = '') -> PoseTrajectory3D:
    """A ``PoseTrajectory3D`` from stamps and :class:`Pose` objects."""
    if len(stamps) != len(poses):
        raise EvaluationError(f'{name or "trajectory"}: {len(stamps)} stamps but {len(poses)} poses')
    if len(poses) == 0:
        raise EvaluationError(f'{name or "trajectory"} is empty')
    return PoseTrajectory3D(poses_se3=[p.matrix() for p in poses], timestamps=np.asarray(stamps, dtype=float),
                            name=name)


def _num(x: float | np.floating | None) -> float | None:
    """JSON-safe float: NaN/inf become None (json.dumps would write invalid JSON otherwise)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _stats(err: np.ndarray) -> dict[str, float | None]:
    err = np.asarray(err, dtype=float)
    if err.size == 0:
        return {'rmse': None, 'mean': None, 'median': None, 'std': None, 'max': None}
    return {'rmse': _num(np.sqrt(np.mean(err**2))), 'mean': _num(err.mean()), 'median': _num(np.median(err)),
            'std': _num(err.std()), 'max': _num(err.max())}


def _evo_stats(metric: metrics.PE) -> dict[str, float | None]:
    s = metric.get_all_statistics()
    return {k: _num(s[k]) for k in ('rmse', 'mean', 'median', 'std', 'max')}


def _alignable(*xyz: np.ndarray) -> bool:
    """Whether evo's Umeyama alignment can run: it squares centred positions and hands their covariance to an
    SVD, which overflows to inf/NaN beyond ~1e154 m, and NumPy's SVD may never return on such input."""
    for p in xyz:
        centred = p - p.mean(axis=0)
        if not (np.all(np.isfinite(centred)) and np.max(np.abs(centred), initial=0.0) < 1e150):
            return False
    return True


def _ape(gt: PoseTrajectory3D, est: PoseTrajectory3D, align: str) -> tuple[dict[str, Any], np.ndarray | None]:
    """APE of the translation part after ``align`` in {'none', 'se3', 'sim3'}; alignment by evo (Umeyama).
    A degenerate trajectory (all points on a line) cannot be aligned: reported, not raised."""
    est = copy.deepcopy(est)
    out: dict[str, Any] = {}
    if align != 'none':
        if not _alignable(gt.positions_xyz, est.positions_xyz):
            return {'error': 'alignment not possible: positions too large for the SVD (beyond 1e150 m from their '
                             'mean)'}, None
        try:
            _, _, s = est.align(gt, correct_scale=(align == 'sim3'))
        except GeometryException as e:
            return {'error': f'alignment not possible: {e}'}, None
        except (np.linalg.LinAlgError, ValueError) as e:     # overflow to inf/NaN in the SVD (absurd positions)
            return {'error': f'alignment not possible: {type(e).__name__}: {e}'}, None
        if align == 'sim3':
            out['scale'] = _num(s)  # evo: est is multiplied by s, so s ~ |gt| / |est|
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    try:
        ape.process_data((gt, est))
    except (metrics.MetricsException, LieAlgebraException, np.linalg.LinAlgError, ValueError) as e:
        return {'error': f'not computable: {type(e).__name__}: {e}'}, None
    out.update(_evo_stats(ape))
    return out, np.asarray(ape.error, dtype=float)


def _rpe(gt: PoseTrajectory3D, est: PoseTrajectory3D, relation: metrics.PoseRelation, delta: float,
         unit: metrics.Unit) -> tuple[dict[str, Any], np.ndarray]:
    """RPE by evo; distance deltas are taken along the ground truth (what "per metre" should mean)."""
    rpe = metrics.RPE(relation, delta=delta, delta_unit=unit, all_pairs=False,
                      pairs_from_reference=(unit == metrics.Unit.meters))
    try:
        rpe.process_data((gt, est))
    except (FilterException, metrics.MetricsException) as e:
        return {'error': str(e)}, np.zeros(0)
    except (LieAlgebraException, np.linalg.LinAlgError, ValueError) as e:   # absurd poses: inf/NaN in products
        return {'error': f'not computable: {type(e).__name__}: {e}'}, np.zeros(0)
    return {**_evo_stats(rpe), 'pairs': len(rpe.error)}, np.asarray(rpe.error, dtype=float)


def associate(est: PoseTrajectory3D, gt: PoseTrajectory3D,
              max_dt: float = DEFAULT_MAX_DT) -> tuple[PoseTrajectory3D, PoseTrajectory3D]:
    """Pairs of poses whose stamps differ by at most ``max_dt`` (evo, nearest stamp); unmatched poses of
    either trajectory are dropped. Returns ``(est, gt)`` of equal length."""
    if max_dt < 0 or not math.isfinite(max_dt):
        raise EvaluationError(f'max_dt must be a finite number >= 0, got {max_dt}')
    try:
        est_s, gt_s = sync.associate_trajectories(est, gt, max_diff=max_dt)
    except sync.SyncException as e:
        raise EvaluationError(str(e)) from None
    return est_s, gt_s


def _anchor_first(traj: PoseTrajectory3D) -> PoseTrajectory3D:
    """Same trajectory re-expressed in its own first frame (first pose = identity)."""
    R, t = traj.poses_se3[0][:3, :3], traj.poses_se3[0][:3, 3]
    inv0 = np.eye(4)                        # closed form: no LU on a matrix that may hold 1e300
    inv0[:3, :3], inv0[:3, 3] = R.T, -R.T @ t
    return PoseTrajectory3D(poses_se3=[inv0 @ p for p in traj.poses_se3], timestamps=traj.timestamps.copy(),
                            name=traj.name)


def evaluate(est_stamps: Sequence[float] | np.ndarray, est_poses: Sequence[Pose],
             gt_stamps: Sequence[float] | np.ndarray, gt_poses: Sequence[Pose], *,
             max_dt: float = DEFAULT_MAX_DT, anchor_first: bool = False, rpe_delta_m: float | None = None,
             name: str = 'estimate') -> Evaluation:
    """Compare an estimate with ground truth (both: pose of base_link in odom, seconds).

    ``anchor_first`` re-expresses both trajectories in their first *associated* pose before the
    unaligned measures: use it when the estimate's ``odom`` is not the ground truth's (it started
    later). ``rpe_delta_m`` adds an RPE over that travelled distance (along the ground truth).
    Raises :class:`EvaluationError` when fewer than 2 poses associate.

    Absurd but finite input (positions of 1e300 m, a diverged estimate) is evaluated as far as floats go: a
    measure that overflows is None in the summary (``_num``), never an exception or a NumPy warning.
    """
    with np.errstate(over='ignore', invalid='ignore', divide='ignore', under='ignore'):
        return _evaluate(est_stamps, est_poses, gt_stamps, gt_poses, max_dt=max_dt, anchor_first=anchor_first,
                         rpe_delta_m=rpe_delta_m, name=name)


def error_growth(stamps: np.ndarray, err: np.ndarray, window_s: float = GROWTH_WINDOW_S) -> dict[str, float | None]:
    """Where a run lost its accuracy: the stretch of at most ``window_s`` over which the unaligned position error
    rose most (``from_s``/``to_s`` after the first stamp, ``growth_m``; the whole run when it is shorter)."""
    t = np.asarray(stamps, float) - float(stamps[0])
    end = np.searchsorted(t, t + window_s, side='right') - 1        # the last stamp within the window of each
    rise = err[end] - err
    k = int(np.argmax(rise))
    return {'from_s': _num(t[k]), 'to_s': _num(t[end[k]]), 'growth_m': _num(rise[k])}


def along_track(est_xyz: np.ndarray, gt_xyz: np.ndarray, back_m: float = HEADING_BACK_M) -> dict[str, float | None]:
    """The final position error split along the true direction of travel at the end (over the last ``back_m`` of
    the true path; positive: the estimate is ahead) and across it: a lost scale shows along the path, a lost heading
    across. None without a direction (a rig that never moved)."""
    steps = _norms(np.diff(gt_xyz, axis=0))
    dist = np.concatenate([[0.0], np.cumsum(steps)])
    i = max(0, int(np.searchsorted(dist, dist[-1] - back_m, side='right')) - 1)
    heading = gt_xyz[-1] - gt_xyz[i]
    n = float(np.linalg.norm(heading))
    if not (np.isfinite(n) and n > 1e-6):
        return {'along_m': None, 'across_m': None}
    off = est_xyz[-1] - gt_xyz[-1]
    along = float(off @ heading) / n
    return {'along_m': _num(along), 'across_m': _num(float(np.linalg.norm(off - along * heading / n)))}


def _norms(v: np.ndarray) -> np.ndarray:
    """Row norms that do not overflow before the result does (|(1e160, 0, 0)| is 1e160, not inf)."""
    return np.hypot(np.hypot(v[:, 0], v[:, 1]), v[:, 2])


def _evaluate(est_stamps: Sequence[float] | np.ndarray, est_poses: Sequence[Pose],
              gt_stamps: Sequence[float] | np.ndarray, gt_poses: Sequence[Pose], *, max_dt: float,
              anchor_first: bool, rpe_delta_m: float | None, name: str) -> Evaluation:
    est_full = to_evo(est_stamps, est_poses, name)
    gt_full = to_evo(gt_stamps, gt_poses, 'ground truth')
    est, gt = associate(est_full, gt_full, max_dt)
    n = est.num_poses
    if n < 2:
        raise EvaluationError(f'{name}: only {n} pose(s) associate with the ground truth within {max_dt} s '
                              f'(need >= 2); check the stamps or --max-dt')
    start_offset = float(_norms(est.positions_xyz[:1] - gt.positions_xyz[:1])[0])
    if anchor_first:
        est, gt = _anchor_first(est), _anchor_first(gt)

    # the papers' measures: no alignment at all
    err = _norms(est.positions_xyz - gt.positions_xyz)
    len_est, len_gt = float(est.path_length), float(gt.path_length)
    position = {**_stats(err), 'terminal': _num(err[-1]),
                'terminal_percent_of_path': _num(100.0 * err[-1] / len_gt) if len_gt > 0 else None,
                'terminal_track': along_track(est.positions_xyz, gt.positions_xyz),
                'largest_growth': error_growth(np.asarray(est.timestamps, float), err)}

    ape: dict[str, Any] = {}
    for align in ('none', 'se3', 'sim3'):
        ape[align], _ = _ape(gt, est, align)

    rpe: dict[str, Any] = {'delta_frames': 1}
    rpe['translation_m'], rpe_t = _rpe(gt, est, metrics.PoseRelation.translation_part, 1, metrics.Unit.frames)
    rpe['rotation_deg'], rpe_r = _rpe(gt, est, metrics.PoseRelation.rotation_angle_deg, 1, metrics.Unit.frames)
    if rpe_delta_m is not None:
        rpe['delta_m'] = float(rpe_delta_m)
        rpe['translation_m_per_delta_m'], _ = _rpe(gt, est, metrics.PoseRelation.translation_part,
                                                    float(rpe_delta_m), metrics.Unit.meters)
        rpe['rotation_deg_per_delta_m'], _ = _rpe(gt, est, metrics.PoseRelation.rotation_angle_deg,
                                                   float(rpe_delta_m), metrics.Unit.meters)

    summary: dict[str, Any] = {
        'name': name,
        'max_dt_s': float(max_dt),
        'anchor_first': bool(anchor_first),
        'poses': {'estimate': est_full.num_poses, 'ground_truth': gt_full.num_poses, 'associated': n},
        'duration_s': _num(est.timestamps[-1] - est.timestamps[0]),
        'start_offset_m': _num(start_offset),
        'position_error_m': position,
        'path_length_m': {'estimate': _num(len_est), 'ground_truth': _num(len_gt),
                          'ratio': _num(len_est / len_gt) if len_gt > 0 else None},
        'ape_translation_m': ape,
        'rpe': rpe,
    }
    return Evaluation(summary=summary, stamps=np.asarray(est.timestamps, dtype=float).copy(),
                      est_xyz=np.asarray(est.positions_xyz, dtype=float).copy(),
                      gt_xyz=np.asarray(gt.positions_xyz, dtype=float).copy(), position_error=err,
                      rpe_translation=rpe_t, rpe_rotation_deg=rpe_r)
