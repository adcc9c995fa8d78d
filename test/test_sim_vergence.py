"""The simulator's vergence step: the left head really verges on the right's fixation point and back (physical),
or only the measurements are made (measurements); the measurement, its stamp and its covariance."""

from __future__ import annotations

import numpy as np
import pytest

from fixego_ros.geometry.rig import default_rig_path, load_rig
from fixego_ros.sim.run import SimSettings, Simulation, resize_rig
from fixego_ros.sim.servo_model import ServoParams, required_readings
from fixego_ros.sim.vergence_measure import VergenceParams, measure, off_axis_deg, sample, tick_times
from fixego_ros.sim.vergence_step import VergenceStep

# the paper loop's first 9 s at 10 Hz: start-up, and the right camera re-selects once (at 7.4 s)
SETTINGS = {'trajectory': 'paper', 'fps': 10.0, 'duration': 9.0, 'texel': 0.006}


@pytest.fixture(scope='module')
def rig():
    return resize_rig(load_rig(default_rig_path()), 160, 120)


def _run(rig, vergence: str) -> tuple[Simulation, list]:
    sim = Simulation(rig, SimSettings(**SETTINGS, vergence=vergence))
    return sim, list(sim.frames())


@pytest.fixture(scope='module')
def physical(rig):
    return _run(rig, 'physical')


@pytest.fixture(scope='module')
def off(rig):
    return _run(rig, 'off')


def _right_changes(frames) -> list[int]:
    """Frames at which the right camera's fixation id changes (plus the first)."""
    ids = [f.states['right'].fixation_id for f in frames]
    return [0] + [k for k in range(1, len(ids)) if ids[k] != ids[k - 1]]


def test_left_head_slews_to_the_right_point_holds_it_and_returns(rig, physical, off):
    sim, frames = physical
    assert isinstance(sim.vergence, VergenceStep)
    steps = sim.vergence.steps
    assert [s.right_fixation_id for s in steps] == [0, 1] and all(s.outcome == 'measured' for s in steps)
    p = ServoParams()
    stamps = np.array([f.t for f in frames])
    pan = np.degrees([f.states['left'].pan_reading for f in frames])            # the joint states as written
    assert np.all(np.abs(np.diff(pan)) / np.diff(stamps) <= p.pan_speed_deg_s + 1.0)   # a slew, not a jump
    own = frames[0].states['left']
    for step in steps:
        k0 = int(np.searchsorted(stamps, step.start))                            # the frame that started it
        m = next(m for m in sim.vergence.measurements if m.right_fixation_id == step.right_fixation_id)
        held = frames[m.frame].states['left']
        right = frames[m.frame].states['right']
        # out: the left head holds the right's point (the ground truth says so, with a new id) ...
        assert np.array_equal(held.point, right.point)
        assert held.fixation_id > frames[k0].states['left'].fixation_id
        want = np.degrees(required_readings(rig, 'left', frames[m.frame].rig_pose, right.point))
        assert abs(np.degrees(held.pan) - want[0]) < 1.0 and abs(np.degrees(held.tilt) - want[1]) < 1.0
        assert np.hypot(*(held.pixel - rig.left.center)) < 2.0 / 57.3 * rig.left.fx
        # ... far from where it looked before: a real slew (tens of degrees), done within the timeout
        assert abs(np.degrees(held.pan) - np.degrees(frames[k0].states['left'].pan)) > 20.0
        assert step.held - step.start < VergenceParams().timeout_s
        # and back: another new id, its own point again, centred; away for a bounded time
        back = frames[int(np.searchsorted(stamps, step.back)) + 1].states['left']
        assert back.fixation_id > held.fixation_id
        assert np.hypot(*(back.pixel - rig.left.center)) < 2.0 / 57.3 * rig.left.fx
        assert step.back - step.start < 2.5
    # the first step returns to the point the left fixated at start-up (still valid): same point, new id
    first_back = frames[int(np.searchsorted(stamps, steps[0].back)) + 1].states['left']
    assert np.array_equal(first_back.point, own.point) and first_back.fixation_id == own.fixation_id + 2
    # between steps the left fixates its own point, never the right's
    for f in frames:
        if f.states['left'].fixation_id in (own.fixation_id, first_back.fixation_id):
            assert not np.array_equal(f.states['left'].point, f.states['right'].point)
    # the left images show the motion; the right camera is not disturbed at all
    k = sim.vergence.measurements[0].frame
    assert not np.array_equal(frames[k].images['left'], off[1][k].images['left'])
    assert all(np.array_equal(a.images['right'], b.images['right']) for a, b in zip(frames, off[1], strict=True))


def test_one_measurement_per_new_right_fixation_at_a_frame_stamp(physical):
    sim, frames = physical
    ms = sim.vergence.measurements
    assert len(ms) == len(_right_changes(frames)) == 2 and not sim.vergence.failures
    attached = [f for f in frames if f.vergence is not None]
    assert [f.vergence for f in attached] == ms                   # each handed out with the frame it refers to
    for m, f in zip(ms, attached, strict=True):
        assert m.frame == f.index and m.t == f.t                   # stamped with that frame's time
        assert m.right_fixation_id == f.states['right'].fixation_id
        # the truth: the right's fixation point in the rig frame at that frame
        assert np.allclose(m.point_true_rig, f.rig_pose.inverse().apply(f.states['right'].point))
        assert m.samples == 2 * VergenceParams().hold_ticks + 1
    assert [f.index for f in frames] == list(range(len(frames)))  # all frames, in order


def test_distance_error_is_within_the_stated_covariance(physical):
    sim, _ = physical
    for m in sim.vergence.measurements:
        assert 1.0 < m.distance_true_m < 5.0
        assert 0.002 * m.distance_true_m < m.std_m < 0.05 * m.distance_true_m      # a few cm at 2-4 m
        assert abs(m.distance_m - m.distance_true_m) < 4.0 * m.std_m
        assert np.all(np.linalg.eigvalsh(m.cov_rig) > 0)                          # invertible
        u = m.point_rig / m.distance_m
        across = np.linalg.norm(np.cross(m.point_rig - m.point_true_rig, u))
        assert across < 0.02 * m.distance_true_m                                  # on the right fixation ray


def test_covariance_matches_the_spread_of_the_error():
    """The stated std is the error's: heads standing still on a point (one quantisation error for the window),
    random sub-unit positions, pixel noise; 300 trials."""
    from fixego_ros.geometry.rotation import Pose
    rig = resize_rig(load_rig(default_rig_path()), 320, 240)
    sp, vp = ServoParams(), VergenceParams()
    rng = np.random.default_rng(3)
    pose = Pose(np.eye(3), np.zeros(3))
    unit = np.radians([1 / sp.pan_units_per_deg, 1 / sp.tilt_units_per_deg])
    X = np.array([1.2, 0.05, 2.8])
    errs, stds = [], []
    for _ in range(300):
        off = {s: rng.uniform(-0.5, 0.5, 2) * unit for s in ('right', 'left')}
        angles = {s: tuple(np.array(required_readings(rig, s, pose, X)) + off[s]) for s in off}
        samples = [sample(rig, sp, pose, X, angles, vp.pixel_sigma_px, rng) for _ in range(5)]
        m = measure(rig, sp, vp, samples, 0, 0.0, X, 0)
        errs.append(m.distance_m - m.distance_true_m)
        stds.append(m.std_m)
    assert 0.8 < np.std(errs) / np.mean(stds) < 1.25 and abs(np.mean(errs)) < 0.3 * np.mean(stds)


def test_measurements_mode_leaves_the_heads_alone(rig, off):
    sim, frames = _run(rig, 'measurements')
    for a, b in zip(frames, off[1], strict=True):
        assert all(np.array_equal(a.images[s], b.images[s]) for s in ('right', 'left'))
        assert a.states['left'].fixation_id == b.states['left'].fixation_id
    changes = _right_changes(frames)
    ms = sim.vergence.measurements
    assert ms and ms[0].frame == changes[0] == 0
    settle = VergenceParams().settle_deg
    for m in ms:                  # one per new right fixation, once the right head is on its point (not before)
        assert frames[m.frame].vergence is m
        k = max(c for c in changes if c <= m.frame)
        st = frames[m.frame].states['right']
        assert m.right_fixation_id == frames[k].states['right'].fixation_id == st.fixation_id
        assert off_axis_deg(rig, 'right', frames[m.frame].rig_pose, st.pan, st.tilt, st.point) <= settle
        assert abs(m.distance_m - m.distance_true_m) < 4.0 * m.std_m and m.std_m < 0.05 * m.distance_true_m
    assert len(ms) + len(sim.vergence.failures) == len(changes)


def test_off_has_no_vergence(off):
    sim, frames = off
    assert sim.vergence is None and all(f.vergence is None for f in frames)
    assert 'vergence' not in SimSettings(**SETTINGS).to_dict()      # its record is the one before vergence existed
    assert SimSettings(**SETTINGS, vergence='physical').to_dict()['vergence'] == 'physical'
    with pytest.raises(ValueError, match='vergence must be one of'):
        SimSettings(vergence='sometimes')


def test_ticks_split_each_frame_interval_evenly():
    ticks = tick_times(1.0, 1.2, 30.0)
    assert len(ticks) == 6 and ticks[-1] == 1.2 and np.allclose(np.diff(ticks), 0.2 / 6)
    assert list(tick_times(0.0, 0.02, 30.0)) == [0.02]           # frames faster than the control: frames only


def test_off_reproduces_the_shipped_walk_bag(tmp_path):
    """The default output without vergence is what it was: the shipped walk bag (vergence off) regenerates."""
    pytest.importorskip('rclpy')
    from fixego_ros.bags.shipped import BAGS_DIR, by_name, compare, generate
    spec = by_name('walk')
    assert spec.settings.vergence == 'off'
    generate(spec, tmp_path / 'walk')
    assert compare(BAGS_DIR / 'walk', tmp_path / 'walk') == []
