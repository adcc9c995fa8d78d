"""Evaluation: TUM files, the papers' and evo's error measures on trajectories with known answers, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fixego_ros.cli import main
from fixego_ros.evaluation.metrics import EvaluationError, evaluate
from fixego_ros.evaluation.tum import TumError, TumWriter, format_tum_line, read_tum, write_tum
from fixego_ros.geometry.rotation import Pose, exp_so3, rot_z

finite = st.floats(min_value=-100.0, max_value=100.0, allow_nan=False)


def helix(n: int = 60, dt: float = 0.1, t0: float = 1000.0) -> tuple[np.ndarray, list[Pose]]:
    """A curved, non-planar path (alignment is well posed), heading along the tangent, starting at identity."""
    stamps = t0 + dt * np.arange(n)
    poses = []
    for i in range(n):
        a = 0.05 * i
        poses.append(Pose(rot_z(a), np.array([np.sin(a) * 2.0, 2.0 - np.cos(a) * 2.0, 0.01 * i])))
    return stamps, poses


# --- TUM files ---------------------------------------------------------------------------------------

@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.lists(finite, min_size=3, max_size=3),
                          st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3)),
                min_size=1, max_size=6),
       st.floats(min_value=0.0, max_value=2e9, allow_nan=False))
def test_tum_round_trip(tmp_path_factory, items, t0):
    stamps = t0 + 0.05 * np.arange(len(items))
    poses = [Pose(exp_so3(np.array(r)), np.array(t)) for t, r in items]
    path = tmp_path_factory.mktemp('tum') / 'x.tum'
    write_tum(path, stamps, poses)
    s2, p2 = read_tum(path)
    np.testing.assert_allclose(s2, stamps, rtol=0, atol=1e-9 + 1e-15 * t0)
    for a, b in zip(poses, p2, strict=True):
        np.testing.assert_allclose(b.t, a.t, atol=1e-9)
        np.testing.assert_allclose(b.R, a.R, atol=1e-9)


def test_tum_deterministic_and_incremental_writer_matches(tmp_path):
    stamps, poses = helix(10)
    a, b = tmp_path / 'a.tum', tmp_path / 'b.tum'
    write_tum(a, stamps, poses)
    with TumWriter(b) as w:
        for s, p in zip(stamps, poses, strict=True):
            w.append(s, p)
            w.flush()
        assert w.count == 10
    assert w.closed
    assert a.read_bytes() == b.read_bytes()
    write_tum(b, stamps, poses)
    assert a.read_bytes() == b.read_bytes()
    assert format_tum_line(1.5, Pose.identity()) == \
        '1.500000000 0.000000000 0.000000000 0.000000000 0.000000000000 0.000000000000 0.000000000000 1.000000000000'
    with pytest.raises(TumError):
        format_tum_line(0.0, Pose(np.eye(3), np.array([np.nan, 0, 0])))


@pytest.mark.parametrize(('body', 'needle'), [
    ('1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n', ':3: expected 8 columns'),
    ('1 0 0 0 0 0 0 1\n2 0 0 x 0 0 0 1\n', ':3: not a number'),
    ('1 0 0 0 0 0 0 1\n2 0 nan 0 0 0 0 1\n', ':3: non-finite'),
    ('1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 0\n', ':3: not a valid quaternion'),
    ('1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n', ':3: stamp'),
])
def test_tum_malformed_names_file_and_line(tmp_path, body, needle):
    path = tmp_path / 'bad.tum'
    path.write_text('# comment\n' + body.replace('\n', '\n\n', 1))  # blank line after line 2 -> bad line is 4
    with pytest.raises(TumError) as e:
        read_tum(path)
    assert str(path) in str(e.value)
    assert needle.replace(':3:', ':4:') in str(e.value)


def test_tum_missing_file(tmp_path):
    with pytest.raises(TumError, match='no such file'):
        read_tum(tmp_path / 'nope.tum')


# --- metrics -----------------------------------------------------------------------------------------

def test_constant_offset():
    stamps, gt = helix()
    off = np.array([0.02, 0.0, 0.0])
    est = [Pose(p.R, p.t + off) for p in gt]
    s = evaluate(stamps, est, stamps, gt).summary
    assert s['position_error_m']['mean'] == pytest.approx(0.02, abs=1e-12)
    assert s['position_error_m']['std'] == pytest.approx(0.0, abs=1e-12)
    assert s['position_error_m']['terminal'] == pytest.approx(0.02, abs=1e-12)
    assert s['ape_translation_m']['none']['rmse'] == pytest.approx(0.02, abs=1e-12)
    assert s['ape_translation_m']['se3']['rmse'] == pytest.approx(0.0, abs=1e-9)
    assert s['path_length_m']['ratio'] == pytest.approx(1.0)
    assert s['rpe']['translation_m']['max'] == pytest.approx(0.0, abs=1e-9)
    assert s['start_offset_m'] == pytest.approx(0.02)
    # anchored at the first associated pose, a constant offset vanishes
    assert evaluate(stamps, est, stamps, gt, anchor_first=True).summary['position_error_m']['max'] < 1e-9
    json.dumps(s, allow_nan=False)


def test_scaled_estimate():
    stamps, gt = helix()
    est = [Pose(p.R, 1.1 * p.t) for p in gt]
    s = evaluate(stamps, est, stamps, gt, rpe_delta_m=0.5).summary
    assert s['path_length_m']['ratio'] == pytest.approx(1.1)
    # evo scales the estimate onto the reference: s = 1 / 1.1
    assert s['ape_translation_m']['sim3']['scale'] == pytest.approx(1 / 1.1, rel=1e-9)
    assert s['ape_translation_m']['sim3']['rmse'] == pytest.approx(0.0, abs=1e-9)
    assert s['ape_translation_m']['se3']['rmse'] > 0.01
    assert s['rpe']['rotation_deg']['max'] == pytest.approx(0.0, abs=1e-6)
    assert s['rpe']['translation_m_per_delta_m']['pairs'] > 0


def test_linear_drift_terminal_is_last():
    stamps, gt = helix(40)
    est = [Pose(p.R, p.t + np.array([0.0, 0.0, 0.001 * i])) for i, p in enumerate(gt)]
    ev = evaluate(stamps, est, stamps, gt)
    np.testing.assert_allclose(ev.position_error, 0.001 * np.arange(40), atol=1e-12)
    pe = ev.summary['position_error_m']
    assert pe['terminal'] == pytest.approx(0.039) and pe['max'] == pytest.approx(0.039)
    assert pe['mean'] == pytest.approx(0.0195)
    assert ev.rpe_translation.shape == (39,)
    np.testing.assert_allclose(ev.rpe_translation, 0.001, atol=1e-9)


def test_association_drops_unmatched():
    stamps, gt = helix(50)
    keep = [i for i in range(50) if i % 5 != 0]
    est_stamps = np.concatenate([stamps[keep] + 0.004, [stamps[-1] + 1.0, stamps[-1] + 2.0]])
    est = [gt[i] for i in keep] + [gt[-1], gt[-1]]
    ev = evaluate(est_stamps, est, stamps, gt, max_dt=0.01)
    assert ev.summary['poses'] == {'estimate': 42, 'ground_truth': 50, 'associated': 40}
    assert ev.position_error.max() < 1e-12
    np.testing.assert_allclose(ev.stamps, stamps[keep] + 0.004)
    # a tighter window pairs nothing
    with pytest.raises(EvaluationError):
        evaluate(est_stamps, est, stamps, gt, max_dt=0.001)


def test_too_short_and_degenerate():
    stamps, gt = helix(5)
    with pytest.raises(EvaluationError, match='need >= 2'):
        evaluate(stamps[:1], gt[:1], stamps, gt)
    # two poses: a line, so alignment is reported impossible rather than raising
    s = evaluate(stamps[:2], gt[:2], stamps, gt).summary
    assert s['poses']['associated'] == 2
    assert 'error' in s['ape_translation_m']['se3']
    json.dumps(s, allow_nan=False)


# --- CLI ---------------------------------------------------------------------------------------------

def test_cli_writes_json_and_png(tmp_path, capsys):
    stamps, gt = helix(30)
    write_tum(tmp_path / 'gt.tum', stamps, gt)
    write_tum(tmp_path / 'est.tum', stamps, [Pose(p.R, p.t + [0.01, 0, 0]) for p in gt])
    write_tum(tmp_path / 'est.raw.tum', stamps, [Pose(p.R, p.t * 1.05) for p in gt])
    rc = main(['eval', str(tmp_path / 'est.tum'), str(tmp_path / 'gt.tum'), '--raw', str(tmp_path / 'est.raw.tum')])
    assert rc == 0
    report = json.loads((tmp_path / 'eval.json').read_text())
    assert report['estimate']['position_error_m']['mean'] == pytest.approx(0.01)
    assert report['raw']['path_length_m']['ratio'] == pytest.approx(1.05)
    assert (tmp_path / 'eval.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 'terminal 1.00 cm' in capsys.readouterr().out

    out = tmp_path / 'o'
    assert main(['eval', str(tmp_path / 'est.tum'), str(tmp_path / 'gt.tum'), '--out', str(out)]) == 0
    assert json.loads((out / 'eval.json').read_text())['raw'] is None
    assert (out / 'eval.png').exists()


def test_cli_errors_exit_2(tmp_path, capsys):
    stamps, gt = helix(5)
    write_tum(tmp_path / 'gt.tum', stamps, gt)
    assert main(['eval', str(tmp_path / 'missing.tum'), str(tmp_path / 'gt.tum')]) == 2
    err = capsys.readouterr().err
    assert err.startswith('fixego eval:') and 'missing.tum' in err and 'Traceback' not in err
    (tmp_path / 'bad.tum').write_text('1 2 3\n')
    assert main(['eval', str(tmp_path / 'bad.tum'), str(tmp_path / 'gt.tum')]) == 2
    assert 'bad.tum:1' in capsys.readouterr().err
    write_tum(tmp_path / 'late.tum', stamps + 100.0, gt)
    assert main(['eval', str(tmp_path / 'late.tum'), str(tmp_path / 'gt.tum')]) == 2
    assert not (tmp_path / 'eval.json').exists()


# --- absurd input (issue 15) ---------------------------------------------------------------------------

def _eval_cli(*args, timeout: float = 120.0):
    """``fixego eval`` in a child process: a hang (NumPy's SVD on inf/NaN may never return) fails, not blocks."""
    import subprocess
    import sys
    return subprocess.run([sys.executable, '-m', 'fixego_ros.cli', 'eval', *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


def _tum(path, rows) -> None:
    path.write_text(''.join(' '.join(str(v) for v in row) + '\n' for row in rows))


@pytest.mark.parametrize('value', ['nan', 'NaN', 'inf', '-inf', '1e999'])
@pytest.mark.parametrize('which', ['estimate', 'ground_truth'])
def test_cli_non_finite_values_fail_naming_file_and_line(tmp_path, capsys, value, which):
    """NaN/inf (1e999 overflows to inf) is not a position: exit 2 with one line naming the file and line."""
    stamps, gt = helix(10)
    write_tum(tmp_path / 'gt.tum', stamps, gt)
    write_tum(tmp_path / 'est.tum', stamps, gt)
    bad = tmp_path / ('est.tum' if which == 'estimate' else 'gt.tum')
    lines = bad.read_text().splitlines()
    fields = lines[5].split()
    fields[2] = value
    lines[5] = ' '.join(fields)
    bad.write_text('\n'.join(lines) + '\n')
    assert main(['eval', str(tmp_path / 'est.tum'), str(tmp_path / 'gt.tum')]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f'{bad}:6:' in err[0] and 'non-finite' in err[0]
    assert not (tmp_path / 'eval.json').exists()


@pytest.mark.parametrize('case', ['one position of 1e160', 'positions near the float limit', 'huge quaternions'])
def test_cli_absurd_finite_values_still_evaluate_and_plot(tmp_path, case):
    """Finite but absurd values (a diverged estimate): the evaluation completes, measures beyond a float are
    n/a (null in the JSON), the figure renders; no traceback, no NumPy warning, no hang."""
    rows = [[0.1 * i, 0.1 * i, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0] for i in range(20)]
    _tum(tmp_path / 'gt.tum', rows)
    est = [list(r) for r in rows]
    if case == 'one position of 1e160':
        est[5][1] = 1e160
    elif case == 'positions near the float limit':
        for i, r in enumerate(est):
            r[1:4] = [1.7e308 if i % 2 else -1.7e308, -1.7e308 if i % 3 else 1.7e308, 1e300]
    else:
        for r in est:
            r[4:8] = [0.0, 0.0, 1e200, 1e200]
    _tum(tmp_path / 'est.tum', est)
    p = _eval_cli(tmp_path / 'est.tum', tmp_path / 'gt.tum', '--raw', tmp_path / 'est.tum', '--anchor-first',
                  '--rpe-delta-m', '0.5', '--out', tmp_path / 'out')
    assert p.returncode == 0, p.stderr
    assert 'Traceback' not in p.stderr and 'Warning' not in p.stderr, p.stderr
    report = json.loads((tmp_path / 'out' / 'eval.json').read_text())       # strict JSON: no NaN/Infinity
    assert (tmp_path / 'out' / 'eval.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    pe = report['estimate']['position_error_m']
    if case == 'one position of 1e160':
        assert pe['max'] == pytest.approx(1e160, rel=1e-9)          # the error itself is a float: reported
        assert pe['rmse'] is None and 'n/a' in p.stdout              # its square is not
    elif case == 'positions near the float limit':
        assert pe['mean'] is None and 'n/a' in p.stdout
    else:          # read as 90 deg about z: anchored in its first pose, the estimate runs along -y, the truth x
        assert report['estimate']['path_length_m']['ratio'] == pytest.approx(1.0)
        assert pe['terminal'] == pytest.approx(1.9 * np.sqrt(2.0))


def test_plot_renders_values_beyond_what_matplotlib_can_scale(tmp_path):
    from fixego_ros.evaluation.metrics import Evaluation
    from fixego_ros.evaluation.plot import plot_evaluation

    n = 6
    xyz = np.array([[1.7e308 * (-1) ** i, -1.7e308, 0.0] for i in range(n)])
    err = np.array([np.inf, 1e308, np.nan, 1.0, 2.0, 3.0])
    ev = Evaluation(summary={'position_error_m': {'mean': None, 'terminal': 3e300}}, stamps=np.arange(n, dtype=float),
                    est_xyz=xyz, gt_xyz=np.zeros((n, 3)), position_error=err)
    out = plot_evaluation(tmp_path / 'p.png', {'refined': ev}, gt_xyz=np.zeros((n, 3)), title='absurd')
    assert out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_tum_quaternions_of_any_scale_read_as_their_rotation(tmp_path):
    path = tmp_path / 'q.tum'
    _tum(path, [[1.0, 0, 0, 0, 0, 0, 1e200, 1e200], [2.0, 0, 0, 0, 0, 0, 1e-200, 1e-200], [3.0, 0, 0, 0, 0, 0, 1, 1]])
    _, poses = read_tum(path)
    assert np.allclose(poses[0].R, poses[2].R) and np.allclose(poses[1].R, poses[2].R)
    assert np.allclose(poses[2].R, rot_z(np.pi / 2))


def test_write_tum_is_atomic(tmp_path, monkeypatch):
    """An interrupted write (Ctrl-C, disk full) leaves the previous file, never half a trajectory."""
    import fixego_ros.evaluation.tum as tum
    stamps, gt = helix(10)
    path = tmp_path / 'est.tum'
    write_tum(path, stamps, gt)
    before = path.read_bytes()

    def interrupted(stamp, pose):
        if stamp > stamps[4]:
            raise KeyboardInterrupt
        return format_tum_line(stamp, pose)

    monkeypatch.setattr(tum, 'format_tum_line', interrupted)
    with pytest.raises(KeyboardInterrupt):
        write_tum(path, stamps, [Pose(p.R, p.t + 1.0) for p in gt])
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ['est.tum']


def test_cli_ctrl_c_is_one_line_and_130(tmp_path, capsys, monkeypatch):
    import fixego_ros.evaluation.metrics as metrics
    stamps, gt = helix(10)
    write_tum(tmp_path / 'gt.tum', stamps, gt)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(metrics, 'evaluate', interrupted)
    assert main(['eval', str(tmp_path / 'gt.tum'), str(tmp_path / 'gt.tum')]) == 130
    assert capsys.readouterr().err == 'fixego eval: interrupted\n'


def test_demo_report_joint_errors_compare_published_and_true_angles_at_the_same_stamps():
    from fixego_ros.demo.report import joint_errors
    assert joint_errors({0.0: (0.0, 0.0)}, {1.0: (0.0, 0.0)}) == {}          # no common stamp: nothing to say
    true = {0.1 * k: (0.0, 0.0) for k in range(5)} | {0.5 + 0.1 * k: (0.05 * (k + 1), 0.0) for k in range(5)}
    est = dict(true)
    est[0.2] = (0.0, np.radians(0.1))            # at rest, 0.1 deg off in tilt
    est[0.7] = (true[0.7][0] - np.radians(0.4), 0.0)   # turning (0.5 rad/s), 0.4 deg behind
    est[9.0] = (0.0, 0.0)                        # no true angle at this stamp: not counted
    e = joint_errors(est, true)
    assert e['frames'] == 10 and e['max_deg'] == pytest.approx(0.4) and e['p50_deg'] == 0.0
    assert e['moving_frames'] == 6 and e['moving_p95_deg'] > e['p95_deg'] - 1e-12
    assert 'beyond_3sigma' not in e                                       # no sigma stated: nothing to say
    # the node's stated 1-sigma: 0 at rest (a reading of a head at rest is exact), 0.1 deg while turning
    sigmas = {t: (0.0, 0.0) if t < 0.45 else (np.radians(0.1), np.radians(0.1)) for t in true}
    e = joint_errors(est, true, sigmas=sigmas)
    # 0.2: 0.1 deg off at a stated 0: beyond; 0.7: 0.4 deg off at 0.1: beyond; the 8 others exact
    assert e['stated_frames'] == 10 and e['beyond_3sigma'] == pytest.approx(0.2)
    # while turning, with a sigma stated (0.5-0.9 s, both axes): one axis 4 sigma off, nine exact
    assert e['moving_error_over_sigma_rms'] == pytest.approx(np.sqrt(16.0 / 10.0))
    sigmas[0.2] = (0.0, np.radians(0.05))
    sigmas[0.7] = (np.radians(0.2), 0.0)
    assert joint_errors(est, true, sigmas=sigmas)['beyond_3sigma'] == 0.0


def test_demo_report_counts_the_frames_where_neither_camera_fixates():
    from fixego_ros.demo.report import blind_frames
    right = {0.1 * k: k not in (3, 4, 5, 8, 9) for k in range(10)}
    left = {0.1 * k: k not in (4, 5, 9) for k in range(10)} | {2.0: False}   # 2.0: the right has no message there
    b = blind_frames({'right': right, 'left': left}, 0.0, 0.9, tail_s=0.25)
    # both without a fixation at 0.4, 0.5 (a run of 2) and 0.9 (in the last 0.25 s); 2.0 lies after the run
    assert (b['frames'], b['blind'], b['longest_run'], b['in_last_s']) == (10, 3, 2, 1)
    assert b['runs'] == [[0.4, 2], [0.9, 1]]
    assert blind_frames({'right': right, 'left': left}, 0.45, 0.85)['blind'] == 1
    assert blind_frames({}, 0.0, 1.0)['frames'] == 0


def test_demo_report_checks_each_vergence_measurement_against_the_true_distance():
    from fixego_ros.demo.report import vergence_accuracy
    cov = np.diag([1e-4, 1e-4, 4e-4])                          # 2 cm std along z
    measured = [(10.0, np.array([0.0, 0.0, 2.02]), cov),       # +2 cm of 2 m: +1 %, one std
                (11.0, np.array([0.0, 0.0, 2.94]), cov),       # -6 cm of 3 m: -2 %, three std
                (12.0, np.array([0.0, 0.0, 2.0]), cov)]        # no truth at its stamp (before the run)
    truth = {10.0: 2.0, 11.0: 3.0}
    acc = vergence_accuracy(measured, 9.0, lambda stamp, point: truth.get(stamp))
    assert (acc['checked'], acc['without_truth']) == (2, 1)
    assert [s['t_s'] for s in acc['steps']] == [1.0, 2.0]
    assert [s['error_cm'] for s in acc['steps']] == pytest.approx([2.0, -6.0])
    assert [s['error_pct'] for s in acc['steps']] == pytest.approx([1.0, -2.0])
    assert [s['error_over_std'] for s in acc['steps']] == pytest.approx([1.0, -3.0])
    assert (acc['abs_error_pct_p50'], acc['abs_error_pct_max']) == pytest.approx((1.5, 2.0))
    assert acc['error_over_std_rms'] == pytest.approx(np.sqrt(5.0))
    assert vergence_accuracy(measured, 0.0, lambda stamp, point: None) == {'checked': 0, 'without_truth': 3,
                                                                            'steps': []}


def test_the_demo_reports_true_distance_follows_the_rig_through_odom_into_the_simulated_room(tmp_path):
    """The truth chain of the demo report: ground_truth/pose (base_link in odom, odom at the trajectory's start) ->
    the rig's pose in the room -> the ray from the right camera along the measured direction."""
    import shutil

    from fixego_ros.demo.report import simulated_distance
    from fixego_ros.geometry.rig import default_rig_path, load_rig
    from fixego_ros.geometry.rotation import rig_pose_to_base_link
    from fixego_ros.sim.trajectories import make_trajectory
    from fixego_ros.sim.world import make_room
    shutil.copy(default_rig_path(), tmp_path / 'rig.yaml')
    mount = load_rig(tmp_path / 'rig.yaml').mount
    traj = make_trajectory('paper', seed=0)
    start, pose = traj.pose_at(0.0), traj.pose_at(9.0)          # mid-loop: turned and moved away from the start
    odom = rig_pose_to_base_link(start.inverse() @ pose, mount)
    at = simulated_distance({'trajectory': 'paper', 'seed': 0, 'duration': 0.0}, tmp_path / 'rig.yaml',
                            [(100.0, odom)])
    world = make_room(0, 0.002)
    for direction in (np.array([0.3, 0.0, 1.0]), np.array([1.0, -0.05, 0.2])):
        u = direction / np.linalg.norm(direction)
        expected, _ = world.raycast(pose.t, pose.R @ u)
        assert 0.5 < expected < 20.0
        assert at(100.0, 1.7 * u) == pytest.approx(expected, abs=1e-9)   # only the direction counts
    assert at(100.5, np.array([0.0, 0.0, 1.0])) is None                  # no truth at that stamp


def test_evaluation_says_where_the_error_came_from():
    """The terminal error along the true direction of travel (a lost scale) and across it (a lost heading), and the
    stretch of the run where the unaligned error grew most."""
    from fixego_ros.evaluation.cli import where_text
    from fixego_ros.evaluation.metrics import along_track, error_growth
    t = np.arange(0.0, 20.0 + 1e-9, 0.1)
    gt = np.column_stack([0.1 * t, np.zeros_like(t), np.zeros_like(t)])          # 0.1 m/s along x
    ahead = 0.1 * np.clip((t - 10.0) / 4.0, 0.0, 1.0)                            # 10 cm ahead, gained in 10-14 s
    est = gt + np.column_stack([ahead, np.full_like(t, 0.02), np.zeros_like(t)])  # and 2 cm to the side
    track = along_track(est, gt)
    assert track['along_m'] == pytest.approx(0.1) and track['across_m'] == pytest.approx(0.02)
    assert along_track(gt - np.array([0.05, 0.0, 0.0]), gt)['along_m'] == pytest.approx(-0.05)     # behind
    assert along_track(gt, np.zeros_like(gt)) == {'along_m': None, 'across_m': None}              # never moved
    err = np.linalg.norm(est - gt, axis=1)
    g = error_growth(t, err, window_s=4.0)
    assert 9.9 <= g['from_s'] <= 10.1 and g['to_s'] == pytest.approx(g['from_s'] + 4.0)
    assert g['growth_m'] == pytest.approx(err[-1] - 0.02, abs=2e-3)
    assert error_growth(t[:5], err[:5], window_s=4.0)['to_s'] == pytest.approx(0.4)   # shorter than the window
    poses = [Pose(np.eye(3), p) for p in est]
    summary = evaluate(t, poses, t, [Pose(np.eye(3), p) for p in gt]).summary['position_error_m']
    assert summary['terminal_track']['along_m'] == pytest.approx(0.1)
    assert where_text(summary).startswith('terminal along the path +10.00 cm, across 2.00 cm; grew most from 10')
