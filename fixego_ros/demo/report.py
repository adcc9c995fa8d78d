"""The demo's report folder: TUM files, evo ATE/RPE, the papers' per-step error, the scale error, the rig's
vergence steps, latency (image -> pose, and by stage) and drops."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fixego_ros.estimation.covariance import std_along
from fixego_ros.estimation.stage_times import Stage
from fixego_ros.evaluation.cli import where_text
from fixego_ros.evaluation.metrics import EvaluationError, evaluate
from fixego_ros.evaluation.plot import plot_evaluation
from fixego_ros.evaluation.tum import write_tum
from fixego_ros.geometry.rotation import Pose, base_link_pose_to_rig

# Papers' Table 1 (real images, 131-step stadium loop): position error in cm
PAPER_TABLE1 = {'raw_mean_cm': 17.51, 'ba_mean_cm': 3.36, 'raw_terminal_cm': 35.0, 'ba_terminal_cm': 4.0}


def _ms(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float) * 1e3
    if not len(a):
        return {}
    return {'p50': float(np.median(a)), 'p95': float(np.percentile(a, 95)), 'max': float(a.max()),
            'mean': float(a.mean())}


def _diag_ms(statuses: dict[str, dict[str, str]], status: str, key: str) -> dict[str, float]:
    """p50/p95 (ms) a node reported on /diagnostics as ``key_p50`` / ``key_p95`` (its last status)."""
    st = statuses.get(status, {})
    try:
        return {q: float(st[f'{key}_{q}']) for q in ('p50', 'p95')}
    except (KeyError, ValueError):
        return {}


# Where every millisecond goes, in pipeline order: (stage, what it measures, where the numbers come from). "after
# the stamp" stages are the arrival (or publish) time minus the image stamp: the simulated rig stamps each image with
# the wall clock as it renders it, so they accumulate; "compute" stages are a node's own time per frame.
STAGES = (
    ('joint_publish', 'after the stamp: camera_node publishes the joint state (the joint wait)',
     'camera_node diagnostics joint_latency_ms, last 300 frames, worse camera'),
    ('joint_state', 'after the stamp: the joint state arrives (+ DDS)', 'recorder, whole run, both cameras'),
    ('fixation', 'after the stamp: the fixation arrives (image DDS + tracking + DDS)', 'recorder, whole run'),
    ('flow_image_in', 'after the stamp: the image arrives at flow_node (DDS of ~300 KB)',
     'flow_node diagnostics image_in_ms, last 300 images'),
    ('flow_image_dds', 'transport: the image published -> received by flow_node (the middleware\'s stamps)',
     'flow_node diagnostics image_dds_ms, last 300 images'),
    ('flow_image_queue', "wait: the image received -> flow_node's callback", 'flow_node diagnostics image_queue_ms, '
     'last 300 images'),
    ('flow_joints_in', "after the stamp: a joint state reaches flow_node's callback (DDS + its queue)",
     'flow_node diagnostics joints_in_ms, last 300 joint states'),
    ('flow_ready', 'after the stamp: flow_node has the stereo frame complete (DDS + synchroniser)',
     'flow_node diagnostics ready_ms, last 300 frames'),
    ('flow_compute', 'compute: flow_node front end + publish', 'flow_node diagnostics process_ms, last 300 frames'),
    ('observation', 'after the stamp: the flow observation arrives (+ DDS)', 'recorder, whole run'),
    ('estimator_queue', "wait: the observation in estimator_node's queue (receive -> callback)",
     'estimator_node diagnostics queue_ms, last 300 observations'),
    ('estimator_in', "after the stamp: the observation reaches estimator_node's callback",
     'estimator_node diagnostics observation_in_ms, last 300 observations'),
    ('estimator_solve', 'compute: estimator_node solve per frame', 'estimator_node diagnostics solve_ms'),
    ('estimator_out', 'after the stamp: estimator_node has published the pose, odometry (and path, TF)',
     'estimator_node diagnostics pose_out_ms, last 300 poses'),
    ('pose', 'after the stamp: the pose arrives', 'recorder, whole run'),
)


def latency_stages(rec) -> dict[str, dict[str, Any]]:
    """The latency breakdown (:data:`STAGES`): p50/p95 in ms per stage, with where it was measured. The hop
    flow -> estimator (DDS + the estimator's queue) is not measured per frame without the estimator's own stamps;
    ``estimator_wait`` gives it by difference of medians (pose - observation - solve), marked as such."""
    st = rec.statuses
    cams = [_diag_ms(st, f'fixego camera_node {side}', 'joint_latency_ms') for side in ('right', 'left')]
    cams = [c for c in cams if c]
    seen = getattr(rec, 'stage_s', {})
    values = {
        'joint_publish': {q: max(c[q] for c in cams) for q in ('p50', 'p95')} if cams else {},
        'joint_state': _ms(seen.get('joint_state_right', []) + seen.get('joint_state_left', [])),
        'fixation': _ms(seen.get('fixation_right', []) + seen.get('fixation_left', [])),
        'flow_image_in': _diag_ms(st, 'fixego flow_node', 'image_in_ms'),
        'flow_image_dds': _diag_ms(st, 'fixego flow_node', 'image_dds_ms'),
        'flow_image_queue': _diag_ms(st, 'fixego flow_node', 'image_queue_ms'),
        'flow_joints_in': _diag_ms(st, 'fixego flow_node', 'joints_in_ms'),
        'flow_ready': _diag_ms(st, 'fixego flow_node', 'ready_ms'),
        'flow_compute': _diag_ms(st, 'fixego flow_node', 'process_ms'),
        'observation': _ms(seen.get('observation', [])),
        'estimator_queue': _diag_ms(st, 'fixego estimator_node', 'queue_ms'),
        'estimator_in': _diag_ms(st, 'fixego estimator_node', 'observation_in_ms'),
        'estimator_solve': _diag_ms(st, 'fixego estimator_node', 'solve_ms'),
        'estimator_out': _diag_ms(st, 'fixego estimator_node', 'pose_out_ms'),
        'pose': _ms(rec.latency_s),
    }
    out: dict[str, dict[str, Any]] = {}
    for name, what, source in STAGES:
        v = values[name]
        out[name] = {**({q: round(v[q], 2) for q in ('p50', 'p95')} if v else {}), 'what': what, 'source': source}
    pose, obs, solve = values['pose'], values['observation'], values['estimator_solve']
    if pose and obs and solve:
        out['estimator_wait'] = {'p50': round(pose['p50'] - obs['p50'] - solve['p50'], 2),
                                 'what': 'flow -> estimator DDS + estimator queue (+ pose DDS)',
                                 'source': 'difference of medians: pose - observation - estimator_solve'}
    return out


VERGENCE_STATUS = 'fixego camera_node left: vergence'
VERGENCE_KEYS = ('attempts', 'successes', 'failures', 'ignored_triggers', 'last_failure', 'last_distance_m',
                 'last_std_m', 'max_interrupted_s', 'total_interrupted_s', 'max_away_s')


def vergence_summary(statuses: dict[str, dict[str, str]], stamps: list[float], t_start: float) -> dict[str, Any]:
    """The rig's vergence steps: the measurements seen on /fixego/vergence (in all, and since the run started)
    and the left camera node's counts from its last /diagnostics status."""
    st = statuses.get(VERGENCE_STATUS, {})
    out: dict[str, Any] = {'measurements': len(stamps), 'measurements_in_run': sum(1 for t in stamps if t >= t_start),
                           'state': st.get('state', 'no status (left camera node not seen)')}
    out.update({k: st[k] for k in VERGENCE_KEYS if k in st})
    return out


def vergence_accuracy(measured: list[tuple[float, np.ndarray, np.ndarray]], t_start: float,
                      true_distance_at: Callable[[float, np.ndarray], float | None]) -> dict[str, Any]:
    """Each vergence measurement (stamp, right fixation point in the rig frame, its covariance) against the true
    distance the simulator gives along the measured direction at its stamp (``true_distance_at``; None where the
    recorder has no truth at that stamp, e.g. before the run). Per measurement: the error (cm, %) and the error in
    units of the std the rig stated along the ray; overall the median and largest |error| in % (issue 17 asks for
    <= 1 % at 2-4 m) and the RMS of error / stated std: about 1 when the covariance the estimator weighs the
    measurement by is honest, below 1 when it is too cautious."""
    steps = []
    for stamp, point, cov in measured:
        true_m = true_distance_at(stamp, point)
        if true_m is None or not math.isfinite(true_m):
            continue
        distance = float(np.linalg.norm(point))
        std = std_along(point, cov)
        err = distance - true_m
        steps.append({'t_s': round(stamp - t_start, 3), 'distance_m': round(distance, 4), 'true_m': round(true_m, 4),
                      'error_cm': round(100 * err, 2), 'error_pct': round(100 * err / true_m, 3),
                      'std_cm': round(100 * std, 2), 'error_over_std': round(err / std, 3) if std > 0 else None})
    out: dict[str, Any] = {'checked': len(steps), 'without_truth': len(measured) - len(steps), 'steps': steps}
    if steps:
        pct = np.abs([s['error_pct'] for s in steps])
        out.update(abs_error_pct_p50=float(np.median(pct)), abs_error_pct_max=float(pct.max()))
        z = [s['error_over_std'] for s in steps if s['error_over_std'] is not None]
        if z:
            out['error_over_std_rms'] = float(np.sqrt(np.mean(np.square(z))))
    return out


def simulated_distance(run_args: dict[str, Any], rig_file: Path,
                       truth: list[tuple[float, Pose]]) -> Callable[[float, np.ndarray], float | None]:
    """``true_distance_at`` for :func:`vergence_accuracy` on the demo's simulated rig: its world (the run's seed,
    sim_rig_node's texel) and the rig's true pose at the stamp, from ``ground_truth/pose`` (base_link in odom, odom
    = base_link at the trajectory's start: the demo holds the rig there until the run starts)."""
    from fixego_ros.geometry.rig import load_rig
    from fixego_ros.pipeline.params import SIM_RIG_NODE_PARAMS
    from fixego_ros.sim.trajectories import make_trajectory
    from fixego_ros.sim.vergence_measure import true_distance
    from fixego_ros.sim.world import make_room

    mount = load_rig(rig_file).mount
    start = make_trajectory(run_args['trajectory'], seed=int(run_args['seed']),
                            duration=float(run_args.get('duration') or 0.0) or None).pose_at(0.0)
    world = make_room(int(run_args['seed']), float(SIM_RIG_NODE_PARAMS['texel'].default))
    at = dict(truth)

    def true_distance_at(stamp: float, point: np.ndarray) -> float | None:
        pose = at.get(stamp)
        return None if pose is None else true_distance(world, start @ base_link_pose_to_rig(pose, mount), point)
    return true_distance_at


def joint_errors(estimated: dict[float, tuple[float, float]], true: dict[float, tuple[float, float]],
                 moving_deg_s: float = 5.0, sigmas: dict[float, tuple[float, float]] | None = None) -> dict[str, float]:
    """Error of the joint states the camera node published against the simulator's true angles at the same image
    stamps (deg, the worse of pan and tilt): p50/p95/max over all frames, and p95 over the frames where the head
    turned faster than ``moving_deg_s`` (from the true angles of neighbouring frames). With the 1-sigma the node
    stated (``sigmas``, rad), the share of those frames where an axis is more than 3 sigma off: whether the
    covariance the back end weighs the readings by is honest. Empty when no stamp matches."""
    stamps = sorted(set(estimated) & set(true))
    if not stamps:
        return {}
    off = np.array([[estimated[t][0] - true[t][0], estimated[t][1] - true[t][1]] for t in stamps])
    err = np.degrees(np.abs(off).max(axis=1))
    ts = np.array(sorted(true))
    q = np.degrees(np.array([true[t] for t in ts]))
    rate = np.zeros(len(ts))
    if len(ts) > 1:
        rate = np.max(np.abs(np.gradient(q, ts, axis=0)), axis=1)
    rate_at = dict(zip(ts.tolist(), rate.tolist(), strict=True))
    moving = np.array([rate_at[t] > moving_deg_s for t in stamps])
    out = {'frames': len(stamps), 'p50_deg': float(np.median(err)), 'p95_deg': float(np.percentile(err, 95)),
           'max_deg': float(err.max()), 'moving_frames': int(moving.sum())}
    if moving.any():
        out['moving_p95_deg'] = float(np.percentile(err[moving], 95))
    stated = [k for k, t in enumerate(stamps) if sigmas and t in sigmas]
    if stated:
        sig = np.array([sigmas[stamps[k]] for k in stated])
        beyond = np.any(np.abs(off[stated]) > 3.0 * sig + 1e-12, axis=1)
        out['stated_frames'] = len(stated)
        out['beyond_3sigma'] = float(beyond.mean())
        # while turning, each axis's error over its stated sigma (1 = the sigma is the error's size; at rest the
        # node states 0 for a head read exactly)
        turning = moving[stated]
        ratio = np.abs(off[stated][turning]) / np.where(sig[turning] > 0.0, sig[turning], np.nan)
        ratio = ratio[np.isfinite(ratio)]
        if ratio.size:
            out['moving_error_over_sigma_rms'] = float(np.sqrt(np.mean(ratio ** 2)))
    return out


def _sigma_scale(camera: dict[str, object]) -> str:
    """What the camera node measured of its predictions at its readings, and the scale its sigmas took from that,
    as its last diagnostics stated them (SigmaCalibration)."""
    measured, scale = camera.get('joint_sigma_measured'), camera.get('joint_sigma_scale')
    if measured is None or scale is None:
        return ''
    return (f' (at its readings the errors measured x{float(measured):.2f} the model\'s sigma over '
            f'{camera.get("joint_sigma_samples", 0)} axes; sigma scaled x{float(scale):.2f})')


def blind_frames(valid: dict[str, dict[float, bool]], t_start: float, t_end: float,
                 tail_s: float = 1.0) -> dict[str, Any]:
    """Frames in [``t_start``, ``t_end``] at which both cameras published "no valid fixation" (``valid``: stamp ->
    valid, per side; a stamp one camera did not publish is not counted): the estimator places such a frame by its
    motion model alone. How many, the longest run of them, and how many in the run's last ``tail_s`` (at the end
    nothing after them corrects them), and each run's start (s after ``t_start``) and length."""
    sides = list(valid.values())
    stamps = sorted(t for t in set.intersection(*(set(v) for v in sides)) if t_start <= t <= t_end) if sides else []
    blind = [not any(v[t] for v in sides) for t in stamps]
    runs: list[list[float]] = []        # [seconds after t_start, frames] of each run of blind frames
    for k, (t, b) in enumerate(zip(stamps, blind, strict=True)):
        if b and k > 0 and blind[k - 1]:
            runs[-1][1] += 1
        elif b:
            runs.append([round(t - t_start, 3), 1])
    return {'frames': len(stamps), 'blind': sum(blind), 'longest_run': max((n for _, n in runs), default=0),
            'in_last_s': sum(b for t, b in zip(stamps, blind, strict=True) if t > t_end - tail_s), 'tail_s': tail_s,
            'runs': runs}


def fast_pose_steps(estimator_status: dict[str, str]) -> dict[str, int]:
    """How the estimator made each frame's pose (its ``steps_<status>`` counters, most first). ``carried``: on the
    smoother's velocity, while its newest answer is within ``LiveSmoother.MAX_CARRY_S`` of the frame (~0.5 ms);
    ``ok`` / ``weak``: a two-frame solve, when the smoother is further behind (2-11 ms on the demo machine, the
    estimator's largest per-frame cost, and the live pose's rotation then comes from it: docs/results.md "Stop 60")."""
    steps = {k.removeprefix('steps_'): int(v) for k, v in estimator_status.items()
             if k.startswith('steps_') and str(v).isdigit()}
    return dict(sorted(steps.items(), key=lambda kv: -kv[1]))


def write_report(out: Path, rec, t_start: float, run_args: dict[str, Any],
                 cpu: dict[str, float] | None = None, inputs: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write ``estimate.live.tum`` (each pose as published), ``estimate.tum`` (the last path: the smoother's
    refined trajectory), ``estimate.raw.tum`` (the last path_raw), ``ground_truth.tum``, ``report.json``,
    ``trajectory.png`` under ``out`` from what the recorder saw at or after ``t_start`` (the vergence measurements:
    all it saw); returns the report (with a ``console`` summary). ``cpu``: % of one core per process over the run
    (:class:`~fixego_ros.demo.cpu.CpuSampler`). The vergence measurements are checked against the simulated world
    when ``out`` holds the run's ``rig.yaml``. ``inputs``: the bag of the estimator's inputs (``bag``, ``messages``
    per topic, ``error``), when one was written."""
    keep = [(i, t, p) for i, (t, p) in enumerate(rec.poses) if t >= t_start]
    live = [(t, p) for _, t, p in keep]
    latency = [rec.latency_s[i] for i, _, _ in keep if i < len(rec.latency_s)]
    est = [(t, p) for t, p in rec.path_poses('path') if t >= t_start]
    raw = [(t, p) for t, p in rec.path_poses('path_raw') if t >= t_start]
    truth = [(t, p) for t, p in rec.truth if t >= t_start]
    files = {}
    for name, traj in (('estimate.live.tum', live), ('estimate.tum', est), ('estimate.raw.tum', raw),
                       ('ground_truth.tum', truth)):
        if traj:
            write_tum(out / name, [t for t, _ in traj], [p for _, p in traj])
            files[name] = len(traj)
    live_stamps = {t for t, _ in live}
    last_live = max(live_stamps, default=0.0)
    dropped = sum(1 for t, _ in truth if t not in live_stamps and t <= last_live)
    # poses whose frame's ground truth the recorder never got (its reader lost it): not scored, and counted so a loss
    # shows here instead of as a frame count that does not add up
    truth_stamps = {t for t, _ in truth}
    without_truth = sum(1 for t in live_stamps if t not in truth_stamps)
    # frames flow_node skipped while behind (it takes the newest ready frame), counted over the node's whole run,
    # so also before the reset
    flow_skipped = rec.statuses.get('fixego flow_node', {}).get('frames_skipped', '?')
    report: dict[str, Any] = {
        'run': {k: str(v) if isinstance(v, Path) else v for k, v in run_args.items() if k != 'func'},
        'files': files,
        'frames': {'rendered': len(truth), 'poses': len(live), 'dropped': dropped, 'flow_skipped': flow_skipped,
                   'poses_without_truth': without_truth},
        'latency_image_to_pose_ms': _ms(latency),
        'latency_stages_ms': latency_stages(rec),
        'cpu_percent_of_one_core': {**(cpu or {}), 'cores': os.cpu_count()},
        'paper_table1_cm': PAPER_TABLE1,
        'diagnostics': dict(rec.statuses),      # each node's last /diagnostics status
        'smoother_done_after_last_pose_s': rec.smoother_catch_up_s,
        'fast_pose_steps': fast_pose_steps(rec.statuses.get('fixego estimator_node', {})),
        'vergence': vergence_summary(rec.statuses, [t for t, _, _ in rec.vergence], t_start),
        'frames_without_fixation': blind_frames(getattr(rec, 'fixation_valid', {}), t_start,
                                                truth[-1][0] if truth else t_start),
        'joint_error_deg': {side: joint_errors({t: q for t, q in rec.joints[side].items() if t >= t_start},
                                               rec.true_joints[side], sigmas=getattr(rec, 'joint_sigmas', {}).get(side))
                            for side in rec.joints},
    }
    if truth and (out / 'rig.yaml').exists():
        report['vergence']['against_truth'] = vergence_accuracy(
            rec.vergence, t_start, simulated_distance(run_args, out / 'rig.yaml', truth))
    evals = {}
    for label, traj in (('refined', est), ('live', live), ('raw', raw)):
        try:
            ev = evaluate([t for t, _ in traj], [p for _, p in traj], [t for t, _ in truth], [p for _, p in truth],
                          anchor_first=True, name=label)
        except EvaluationError as e:
            report[label] = {'error': str(e)}
            continue
        evals[label] = ev
        report[label] = dict(ev.summary)
        pl = ev.summary.get('path_length_m', {})
        if pl.get('ground_truth'):
            # the metric scale the rig measured (vergence): estimated / true path length - 1
            report[label]['scale_error'] = float(pl['estimate']) / float(pl['ground_truth']) - 1.0
    if evals and truth:
        gt_xyz = np.array([p.t for _, p in truth])
        plot_evaluation(out / 'trajectory.png', evals, gt_stamps=np.array([t for t, _ in truth]),
                        gt_xyz=gt_xyz - gt_xyz[0], title=f'fixego demo: {run_args.get("trajectory", "")}')
        report['files']['trajectory.png'] = 1
    lines = [f'fixego demo report: {out}',
             f'  frames rendered {len(truth)}, poses {len(live)}, dropped {dropped} (flow_node skipped '
             f'{flow_skipped} while behind, counted from its start)'
             + (f'; {without_truth} poses without a recorded ground truth (the recorder lost it)' if without_truth
                else '')]
    lat = report['latency_image_to_pose_ms']
    if lat:
        lines.append(f'  latency image -> pose: p50 {lat["p50"]:.1f} ms, p95 {lat["p95"]:.1f} ms, '
                     f'max {lat["max"]:.1f} ms')
    stages = [f'{k} {v["p50"]:.1f}' + (f'/{v["p95"]:.1f}' if 'p95' in v else '')
              for k, v in report['latency_stages_ms'].items() if 'p50' in v]
    if stages:
        lines.append('  latency by stage, ms p50/p95 (see report.json): ' + ', '.join(stages))
    if cpu:
        lines.append(f'  CPU, % of one core ({os.cpu_count()} cores): '
                     + ', '.join(f'{k} {v:.0f}' for k, v in cpu.items()))
    for label in ('raw', 'live', 'refined'):
        s = report.get(label, {})
        if 'error' in s:
            lines.append(f'  {label}: {s["error"]}')
            continue
        pe, pl, ape = s['position_error_m'], s['path_length_m'], s['ape_translation_m']
        se3 = ape['se3'].get('rmse') if isinstance(ape.get('se3'), dict) else None
        lines.append(f'  {label:8s} position error mean {100 * pe["mean"]:.2f} cm (std {100 * pe["std"]:.2f}), '
                     f'terminal {100 * pe["terminal"]:.2f} cm; ATE SE(3) '
                     + (f'{100 * se3:.2f} cm' if se3 is not None else 'n/a')
                     + f'; path length {pl["estimate"]:.2f} / {pl["ground_truth"]:.2f} m'
                     + (f' (scale error {100 * s["scale_error"]:+.1f} %)' if 'scale_error' in s else ''))
        if label == 'refined' and 'terminal_track' in pe:
            lines.append(f'           {where_text(pe)}')
    v = report['vergence']
    lines.append(f'  vergence: {v["measurements"]} measurements ({v["measurements_in_run"]} during the run); left '
                 f'camera steps {v.get("successes", "?")}/{v.get("attempts", "?")} done, interrupted at most '
                 f'{v.get("max_interrupted_s", "?")} s' + (f'; last failure: {v["last_failure"]}'
                                                          if v.get('last_failure') else ''))
    acc = v.get('against_truth', {})
    if acc.get('checked'):
        errors = ', '.join(f'{st["error_cm"]:+.1f}' for st in acc['steps'])
        lines.append(f'  vergence against the true distance: {acc["checked"]} measurements, error {errors} cm '
                     f'(|error| p50 {acc["abs_error_pct_p50"]:.2f} %, max {acc["abs_error_pct_max"]:.2f} %)'
                     + (f'; error / stated std RMS {acc["error_over_std_rms"]:.2f} (1: the stated std is honest)'
                        if 'error_over_std_rms' in acc else ''))
    b = report['frames_without_fixation']
    if b['frames']:
        lines.append(f'  frames with no fixation in either camera (placed by the motion model): {b["blind"]} of '
                     f'{b["frames"]}, longest run {b["longest_run"]}, {b["in_last_s"]} in the last {b["tail_s"]:g} s')
    est = report['diagnostics'].get('fixego estimator_node', {})
    if 'smoother_restarts' in est:      # numerical health of the back end (its last /diagnostics status), its lag
        done = report['smoother_done_after_last_pose_s']
        lines.append(f'  smoother: {est["smoother_restarts"]} restarts, {est.get("smoother_repairs", "?")} repairs, '
                     f'{est.get("smoother_dropped_landmarks", "?")} landmarks dropped behind a camera, '
                     f'{est.get("smoother_resections_rejected", "?")} resections rejected, '
                     f'{est.get("smoother_vergence_used", "?")} vergence measurements used, '
                     f'{est.get("smoother_results", "?")} frames smoothed and '
                     f'{est.get("smoother_skipped_frames", "?")} left out (one per 0.1 s goes in, fewer when behind), '
                     f'p50 {est.get("smoother_update_ms_p50", "?")} / p95 {est.get("smoother_update_ms_p95", "?")} '
                     f'ms per frame smoothed; its newest '
                     f'result behind the newest frame p50 {est.get("smoother_behind_s_p50", "?")} / p95 '
                     f'{est.get("smoother_behind_s_p95", "?")} s (last 300 frames); '
                     + (f'done {done:.1f} s after the last pose' if done is not None
                        else 'not done within the wait after the last pose (the path ends in fast poses)'))
        stages = [(stage.value, est.get(f'smoother_{stage.value}_ms_p50')) for stage in Stage]
        if any(ms is not None for _, ms in stages):
            lines.append('  smoother ms per frame smoothed by stage, p50: '
                         + ', '.join(f'{name} {ms}' for name, ms in stages if ms is not None))
    if report['fast_pose_steps']:
        lines.append('  fast poses by step (carried: on the smoother\'s velocity, it close behind; ok/weak: solved, '
                     'it further behind): ' + ', '.join(f'{k} {v}' for k, v in report['fast_pose_steps'].items()))
    je = [f'{side} p50 {e["p50_deg"]:.3f}, p95 {e["p95_deg"]:.3f}, max {e["max_deg"]:.3f}'
          + (f', p95 {e["moving_p95_deg"]:.3f} while turning' if 'moving_p95_deg' in e else '')
          + (f', {100 * e["beyond_3sigma"]:.1f} % beyond 3 stated sigma' if 'beyond_3sigma' in e else '')
          + (f', error / stated sigma RMS {e["moving_error_over_sigma_rms"]:.2f} while turning'
             if 'moving_error_over_sigma_rms' in e else '')
          + _sigma_scale(report['diagnostics'].get(f'fixego camera_node {side}', {}))
          for side, e in report['joint_error_deg'].items() if e]
    if je:
        lines.append('  joint states against the true angles, deg: ' + '; '.join(je))
    if inputs is not None:
        report['estimator_inputs'] = inputs
        counts = ', '.join(f'{t} {n}' for t, n in inputs['messages'].items())
        lines.append(f'  estimator inputs: {inputs["bag"]} ({counts})'
                     + (f'; ERROR: {inputs["error"]}' if inputs['error'] else
                        f'; replay them: fixego replay {inputs["bag"]} --out EST.tum'))
    lines.append('  papers (real images): raw 17.51 cm mean / ~35 cm terminal; local BA 3.36 cm / ~4 cm')
    report['console'] = '\n'.join(lines)
    (out / 'report.json').write_text(json.dumps({k: v for k, v in report.items() if k != 'console'}, indent=1))
    (out / 'report.txt').write_text(report['console'] + '\n')
    return report
