"""The metric back end (fixed-lag smoother) on point-level runs with persistent landmarks (no images)."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from conftest import perturb_resection
from scipy.spatial.transform import Rotation

from fixego_ros.estimation.backend import make_backend
from fixego_ros.estimation.config import EstimatorConfig
from fixego_ros.estimation.factors import TwoFrameStep
from fixego_ros.estimation.fixed_lag import FixedLagWindow
from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.estimation.keys import LandmarkKind
from fixego_ros.estimation.smoother import Smoother
from fixego_ros.estimation.status import StepStatus
from fixego_ros.estimation.twoframe import SolverConfig
from fixego_ros.experiments.landmark_scene import LandmarkScene, LandmarkSceneConfig
from fixego_ros.geometry.rig import make_rig
from fixego_ros.sim.trajectories import make_trajectory

RIG = make_rig(640, 480, 21.0, 0.2)
F = RIG.camera('right').fx


def _config(**smoother) -> EstimatorConfig:
    base = EstimatorConfig(solver=SolverConfig(sigma=1.0 / F))
    return dataclasses.replace(base, smoother=dataclasses.replace(base.smoother, **smoother))


@pytest.fixture(scope='module')
def loop():
    """12 s of the papers' loop (a straight into the first arc) at 5.1 Hz, 0.3 px noise."""
    scene = LandmarkScene(RIG, LandmarkSceneConfig(noise_px=0.3, max_tracks=40))
    return scene.run(make_trajectory('paper'), duration=12.0)


def _vergence(run, k: int, rel_std: float, rng: np.random.Generator):
    """The right fixation point at frame ``k`` as the vergence step measures it (range noise ``rel_std``)."""
    p = run.fixation_points[k]['right']
    d = float(np.linalg.norm(p))
    u = p / d
    cov = np.eye(3) * (1e-3 * d) ** 2 + np.outer(u, u) * (rel_std * d) ** 2
    return p * (1.0 + rng.normal(0.0, rel_std)), cov


def _replay(smoother: Smoother, run, vergence: bool = True, speed: bool = False, speed_bias: float = 0.0,
            aids_from_s: float = 0.0):
    """Feed every frame (and the aids; the speed source reads ``1 + speed_bias`` times the truth; vergence at each new
    right fixation; both from ``aids_from_s`` into the run on), keep the path as a caller does: the positions so far
    times each result's ``prefix_scale``, then its pose and its revisions."""
    rng = np.random.default_rng(3)
    path: dict[float, np.ndarray] = {}
    results = []
    last_fid = None
    for k, obs in enumerate(run.observations):
        aided = obs.stamp - run.stamps[0] >= aids_from_s
        if speed and aided:
            pose0 = run.poses[max(k - 1, 0)]
            v = (pose0.inverse() @ run.poses[k]).t / max(obs.stamp - run.stamps[max(k - 1, 0)], 1e-9)
            smoother.add_velocity(obs.stamp - 1e-3, v * (1.0 + speed_bias + rng.normal(0.0, 0.01)), np.eye(3) * 1e-4)
        r = smoother.update(obs)
        fid = obs.right.fixation_id
        if vergence and fid != last_fid and aided:
            smoother.add_fixation_point(obs.stamp, 'right', *_vergence(run, k, 0.005, rng))
            last_fid = fid
        results.append(r)
        path = {s: p * r.prefix_scale for s, p in path.items()}
        path[r.stamp] = r.pose.t
        for s, p in r.revised:
            path[s] = p.t
    est = np.array([path[s] for s in run.stamps])
    true = np.array([p.t for p in run.poses])
    return results, est, true


def _length(x: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(x, axis=0), axis=1)))


def test_vergence_measurements_make_the_loop_metric(loop):
    """The path length comes out near right (the scale is measured). The shape on this point-level scene was the
    known weak case, ~18 cm mean after 12 s (a yaw of the rig looks like a sideways translation to both narrow
    cameras); the forward-motion prior pins that mode: 3.0 cm, length x0.95 (x0.91 without it; docs/results.md
    "Stop 55")."""
    results, est, true = _replay(Smoother(RIG, _config()), loop)
    err = np.linalg.norm(est - true, axis=1)
    assert err.mean() < 0.1, err.mean()
    assert abs(_length(est) / _length(true) - 1.0) < 0.1
    assert all(np.all(np.isfinite(r.pose_covariance)) for r in results)
    assert results[-1].scale_observed and 'vergence' in results[-1].scale_note
    assert results[0].status is StepStatus.INIT and all(r.placed for r in results)


def test_without_an_aid_the_scale_is_unobserved_and_said_so(loop):
    """The nominal speed sets the gauge: the path follows the nominal length, not the true one, and the results say
    the scale is unobserved, with a position covariance to match. (The length is a gauge: 1.05x the nominal on this
    scene before stop 31's step-direction factor, ~1.9x after it, 0.65x with stop 55's forward-motion prior, whose
    log-space length gauge keeps it from shrinking further: 0.23x without.)"""
    results, est, true = _replay(Smoother(RIG, _config(nominal_speed=1.0)), loop, vergence=False)
    assert not any(r.scale_observed for r in results)
    assert 'unobserved' in results[-1].scale_note
    assert results[-1].pose_covariance[3, 3] > 1.0
    duration = loop.stamps[-1] - loop.stamps[0]
    assert _length(est) > 1.5 * _length(true)              # the true speed is ~0.3 m/s, the nominal 1 m/s
    assert 0.5 * duration < _length(est) < 2.5 * duration     # the nominal length's order, whatever the truth


@pytest.mark.parametrize('stretch', [True, False])
def test_the_first_measurement_stretches_the_path_that_left_the_window_before_it(loop, monkeypatch, stretch):
    """Nominal speed 1 m/s, the rig's ~0.3 m/s, and a speed source that starts 4 s into the run: the path before it
    was built at the nominal speed, and what had left the 2 s window by then no solve moves. Once the rig's speed since
    the aid is known, the smoother reports the stretch once (``prefix_scale``, below 1 here), and the path goes on from
    the stretched part without a jump. Control: without the stretch that part keeps the nominal speed. (The window is
    2 s here whatever the default: the scene is 12 s long, and with a 3 s window only the first second, the least
    regular, would have left it.)"""
    if not stretch:
        monkeypatch.setattr(Smoother, 'STRETCH_RANGE', (1.0, 1.0))
    sm = Smoother(RIG, _config(nominal_speed=1.0, lag_s=2.0))
    results, est, true = _replay(sm, loop, vergence=False, speed=True, aids_from_s=4.0)
    scales = [r.prefix_scale for r in results if r.prefix_scale != 1.0]
    t = np.array(loop.stamps) - loop.stamps[0]
    left = t < 4.0 - sm.settings.lag_s - 0.1              # frames that had left the window before the aid
    ratio = _length(est[left]) / _length(true[left])
    boundary = int(np.flatnonzero(left)[-1])
    steps = np.linalg.norm(np.diff(est, axis=0), axis=1)
    if stretch:
        assert len(scales) == 1 and 0.2 < scales[0] < 0.8, scales      # measured 0.316
        assert 'stretched' in results[-1].scale_note
        assert abs(ratio - 1.0) < 0.4, ratio                 # measured 1.12 (the nominal-speed part was not one
        # scale: x3.8 in its first second, x2.7 in its last); no jump where it meets the graph's frames
        assert steps[boundary] < 2.0 * max(steps[boundary - 1], steps[boundary + 1])
    else:
        assert not scales and ratio > 3.0, ratio             # measured 3.53
    assert np.all(np.isfinite(est))


def _twist_sigmas(bag: str, monkeypatch) -> np.ndarray:
    """The rotation sigma of every constant-twist factor the smoother adds in a replay of shipped bag ``bag``."""
    from fixego_ros.bags.shipped import BAGS_DIR
    from fixego_ros.bench.replay import replay_bag
    from fixego_ros.estimation.factors import ConstantTwist
    seen = []
    factor = ConstantTwist.factor

    def spy(self, frames, dt1, dt2, measured=False, rotation_sigma=None):
        seen.append(self.rotation_sigma if rotation_sigma is None else max(rotation_sigma, self.rotation_sigma))
        return factor(self, frames, dt1, dt2, measured, rotation_sigma)

    monkeypatch.setattr(ConstantTwist, 'factor', spy)
    replay_bag(BAGS_DIR / bag, 1)
    return np.array(seen)


def test_the_twist_prior_loosens_its_rotation_for_a_rig_that_turns_irregularly(monkeypatch):
    """The wheeled rig of the papers' loop keeps the configured rotation sigma on almost every frame (a straight
    meeting an arc changes its rate once, which the median spread ignores); the walker's head bob and sway loosen it
    nine times over (Smoother.RATE_SPREAD_GAIN). Measured: 92 % of the loop's factors at 0.1 rad/s, the walk's median
    0.95."""
    base = EstimatorConfig().smoother.twist_rotation_sigma
    wheeled, walked = _twist_sigmas('paper', monkeypatch), _twist_sigmas('walk', monkeypatch)
    assert np.all(wheeled >= base) and np.all(walked >= base)
    assert np.mean(wheeled == base) > 0.8, np.mean(wheeled == base)
    assert np.median(walked) > 5.0 * base > np.median(wheeled), (np.median(walked), np.median(wheeled))


def test_a_speed_source_makes_the_loop_metric(loop):
    results, est, true = _replay(Smoother(RIG, _config()), loop, vergence=False, speed=True)
    assert results[-1].scale_observed and 'speed source' in results[-1].scale_note
    assert abs(_length(est) / _length(true) - 1.0) < 0.05
    assert np.linalg.norm(est - true, axis=1).mean() < 0.05


def test_vergence_measures_the_speed_sources_scale_bias(loop):
    """Wheel odometry 4 % long (a wheel radius off, which its covariance does not show): alone, its scale is held at
    1 and the path comes out that much long (the rays' own scale is biased, so they must not calibrate it); with the
    vergence measurements the graph estimates the source's scale near 1 / 1.04 and the path's length follows."""
    held = Smoother(RIG, _config())
    _, est, true = _replay(held, loop, vergence=False, speed=True, speed_bias=0.04)
    assert held.speed_scale == 1.0 and 'held at x1.000' in held.scale_note() and not held.speed_scale_estimated
    ratio_held = _length(est) / _length(true)
    assert ratio_held > 1.025                                  # measured 1.04
    both = Smoother(RIG, _config())
    results, est, true = _replay(both, loop, vergence=True, speed=True, speed_bias=0.04)
    assert abs(both.speed_scale * 1.04 - 1.0) < 0.02           # measured 0.958 (true 0.962), path x0.997
    assert abs(_length(est) / _length(true) - 1.0) < abs(ratio_held - 1.0) - 0.01
    assert 'its scale estimated x0.9' in results[-1].scale_note and both.speed_scale_estimated
    fixed = Smoother(RIG, _config(speed_scale_sigma=0.0))      # the source taken as exact: its bias stays
    _replay(fixed, loop, vergence=True, speed=True, speed_bias=0.04)
    assert fixed.speed_scale == 1.0


def test_step_directions_are_held_between_keyframes_only(loop, monkeypatch):
    """A frame the front end does not keep as a keyframe still gets its two-frame step, but not a direction factor:
    its baseline is short and it reuses its keyframe's rays (30 Hz loop 12.3 -> 5.2 cm, circle 20.6 -> 1.6 cm mean).
    Every other frame of the loop is marked a non-keyframe here; the direction is asked for the keyframes only."""
    sm = Smoother(RIG, _config())
    asked: list[int] = []
    factor = sm.direction.factor
    monkeypatch.setattr(sm.direction, 'factor', lambda ref, i, *a, **k: asked.append(i) or factor(ref, i, *a, **k))
    for k, obs in enumerate(loop.observations[:12]):
        r = sm.update(dataclasses.replace(obs, keyframe=k % 2 == 0))
        assert r.placed and r.pose.is_finite()
    assert asked and all(i % 2 == 0 for i in asked)   # smoother frame i is loop frame i (one graph, no restart)
    assert len(asked) >= 4


def test_revisions_are_earlier_frames_inside_the_lag(loop):
    sm = Smoother(RIG, _config(lag_s=1.0))
    for obs in loop.observations[:20]:
        r = sm.update(obs)
    stamps = [s for s, _ in r.revised]
    assert stamps == sorted(stamps) and stamps[-1] < r.stamp
    assert r.stamp - stamps[0] <= 1.0 + 0.25                 # the lag, and at most one frame more
    assert len(stamps) >= 4


def test_same_input_same_trajectory(loop):
    a = [r.pose.t for r in _replay(Smoother(RIG, _config()), loop)[0]]
    b = [r.pose.t for r in _replay(Smoother(RIG, _config()), loop)[0]]
    assert np.array_equal(np.array(a), np.array(b))


def test_bad_frames_and_measurements_are_refused_without_harm(loop):
    sm = Smoother(RIG, _config())
    obs = loop.observations
    for o in obs[:6]:
        sm.update(o)
    before = sm.last_stamp
    again = sm.update(obs[3])                                # out of order
    assert not again.placed and again.status is StepStatus.REJECTED and sm.last_stamp == before
    # a frame nothing constrains: no camera at all; predicted by the motion prior, finite
    blind = sm.update(FrameObservation(obs[6].stamp, None, None, obs[5].stamp, True))
    assert blind.status is StepStatus.PREDICTED and blind.pose.is_finite()
    # a camera whose rays are NaN is left out, not propagated
    cam = obs[7].right
    nan = CameraFrame(np.full(3, np.nan), cam.fixation_id, cam.cam_to_rig, track_ids=cam.track_ids,
                      track_rays=np.full_like(cam.track_rays, np.nan))
    r = sm.update(FrameObservation(obs[7].stamp, nan, obs[7].left, obs[6].stamp, True))
    assert r.pose.is_finite() and np.all(np.isfinite(r.pose_covariance))
    with pytest.raises(ValueError):
        sm.add_fixation_point(obs[7].stamp, 'right', np.array([np.nan, 0.0, 1.0]), np.eye(3))
    with pytest.raises(ValueError):
        sm.add_fixation_point(obs[7].stamp, 'right', np.array([0.0, 0.0, 3.0]), -np.eye(3))
    with pytest.raises(ValueError):
        sm.add_velocity(obs[7].stamp, np.zeros(3), np.zeros((3, 3)))
    for o in obs[8:30]:
        sm.update(o)
    sm.add_fixation_point(obs[2].stamp, 'right', np.array([0.0, 0.0, 3.0]), np.eye(3) * 1e-4)   # long gone
    assert 'ignored' in sm.scale_note() and not sm.scale_observed and sm.vergence_used == 0


def test_the_factory_gives_the_papers_method_on_request():
    assert type(make_backend(RIG, EstimatorConfig())).__name__ == 'LiveSmoother'
    assert type(make_backend(RIG, EstimatorConfig(refinement='local'))).__name__ == 'Estimator'


def test_a_vergence_point_off_the_fixation_ray_is_not_used(loop):
    """A measurement of another point than the one the camera fixates (here 3 deg off its ray, ~45 px) would pull
    the fixation landmark, and the trajectory with it; it is refused with a note, the same point on the ray is
    used."""
    sm = Smoother(RIG, _config())
    for obs in loop.observations[:8]:
        sm.update(obs)
    point, cov = _vergence(loop, 7, 0.0, np.random.default_rng(0))
    center = RIG.center('right')
    a = math.radians(3.0)
    turn = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    sm.add_fixation_point(loop.stamps[7], 'right', center + turn @ (point - center), cov)
    later = [obs for obs in loop.observations[8:] if obs.stamp <= loop.stamps[7] + Smoother.CARRY_MAX_S + 0.2]
    for obs in later:                   # (kept a while: a later frame's fixation might be the measured point)
        sm.update(obs)
    assert later[-1].stamp > loop.stamps[7] + Smoother.CARRY_MAX_S
    assert not sm.scale_observed and 'px off the right fixation ray' in sm.scale_note()
    sm.add_fixation_point(loop.stamps[7], 'right', point, cov)
    assert sm.scale_observed


def _off_ray(obs, previous_id: int):
    """The frame's right fixation as a passive tracker that still follows another point gives it: 3 deg off."""
    a = math.radians(3.0)
    turn = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    return dataclasses.replace(obs, right=dataclasses.replace(obs.right, fixation_ray=turn @ obs.right.fixation_ray,
                                                              fixation_id=previous_id))


@pytest.mark.parametrize('gap', ['skipped', 'single_camera', 'off_ray'])
def test_a_vergence_point_whose_frame_is_missing_or_lacks_the_camera_is_carried_to_a_neighbour(loop, gap):
    """The live back end skips frames to keep up, a loaded flow_node sends frames with one camera, a replay's
    passive tracker re-selects the measured point only on the next frame, and a measurement arrives after its frame:
    it is moved into a nearby frame with the right fixation (the motion between interpolated) and still used."""
    sm = Smoother(RIG, _config())
    rng = np.random.default_rng(3)
    last_fid, pending, given = None, None, 0
    for k, obs in enumerate(loop.observations):
        fid = obs.right.fixation_id
        skip = fid != last_fid and k > 0
        previous = last_fid
        if fid != last_fid:
            pending, last_fid = (obs.stamp, *_vergence(loop, k, 0.005, rng)), fid
        if skip and gap == 'skipped':
            continue                    # the measured frame never reaches the smoother
        if skip and gap == 'off_ray':
            obs = _off_ray(obs, previous)
        elif skip:
            obs = dataclasses.replace(obs, right=None)
        sm.update(obs)
        if pending is not None:
            sm.add_fixation_point(pending[0], 'right', pending[1], pending[2])
            pending, given = None, given + 1
    assert given >= 2 and sm.scale_observed           # one at frame 0, the others carried
    assert f'({given} vergence measurement(s))' in sm.scale_note() and sm.vergence_used == given
    assert sm.restarts == 0


def _rest_then_move(loop, n_rest: int = 10):
    """``n_rest`` frames standing at the loop's first pose (zero flow), then the loop: the live demo's start (it
    measures the scale at rest before the rig moves)."""
    first = loop.observations[0]
    still = {side: dataclasses.replace(cam, flow_prev=cam.track_rays, flow_curr=cam.track_rays)
             for side, cam in (('right', first.right), ('left', first.left))}
    t0 = first.stamp - 0.2 * n_rest
    rest = [dataclasses.replace(first, stamp=t0 + 0.2 * k, prev_stamp=None if k == 0 else t0 + 0.2 * (k - 1),
                                **still) for k in range(n_rest)]
    moving = list(loop.observations)
    moving[0] = dataclasses.replace(moving[0], prev_stamp=rest[-1].stamp)
    return rest, dataclasses.replace(loop, observations=moving)


def _stand_still(loop, rest) -> tuple[Smoother, list]:
    """A smoother fed the frames standing still, with a vergence measurement at the fourth (the demo's scale at
    rest); and its results."""
    sm = Smoother(RIG, _config())
    rng = np.random.default_rng(3)
    results = []
    for k, obs in enumerate(rest):
        results.append(sm.update(obs))
        if k == 3:
            sm.add_fixation_point(obs.stamp, 'right', *_vergence(loop, 0, 0.005, rng))
    return sm, results


def test_at_rest_the_graph_holds_and_keeps_the_scale(loop):
    """A rig standing still (the live demo measures its scale at rest before it moves): landmarks seen from one
    place have no depth information. Tracks wait for a baseline (stop 31; before, they entered at the far guess
    once seen patient_views times and made the system indeterminate without a depth prior); the fixation points
    enter at once, with a depth prior, and the graph holds without a restart."""
    sm, results = _stand_still(loop, _rest_then_move(loop, 25)[0])
    assert all(r.pose.is_finite() and np.linalg.norm(r.pose.t) < 0.05 for r in results)
    assert sm.restarts == 0 and sm.scale_observed
    assert {lid.kind for lid in sm._landmarks} == {LandmarkKind.FIXATION}


def test_frames_whose_keyframe_predates_the_graph_step_from_the_newest_frame(loop):
    """Stop 41. The live node resets the smoother while the front end keeps its keyframe (and a live child skips
    keyframes): the frames' flow starts from a frame the graph never had. They had no two-frame step, only a few
    fixation landmarks and the motion prior, and in 7 of 57 demo runs the rig standing still turned 6-33 deg in
    its first second. They now step from the newest frame over the tracks both saw."""
    rest, _ = _rest_then_move(loop, 15)
    rng = np.random.default_rng(5)
    before = rest[0].stamp - 1.0                          # the front end's keyframe, before the reset

    def noisy(cam):
        rays = cam.track_rays + rng.normal(0.0, 0.05 / F, cam.track_rays.shape)   # a tracker at rest
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return dataclasses.replace(cam, track_rays=rays, flow_curr=rays)

    sm = Smoother(RIG, _config())
    results = [sm.update(dataclasses.replace(obs, prev_stamp=before, keyframe=False,
                                             right=noisy(obs.right), left=noisy(obs.left))) for obs in rest]
    assert all(r.status is StepStatus.STATIONARY for r in results[1:])
    assert all('stepped from the last frame' in r.message for r in results[1:])
    turned = max(np.degrees(np.linalg.norm(r.pose.rvec())) for r in results)
    assert turned < 0.05 and sm.restarts == 0


def _old_direction_floor(monkeypatch) -> None:
    """The step-direction factor's length floor before stop 52: 1 um (at the loop's 5.1 Hz and the nominal speed)."""
    from fixego_ros.estimation.factors import StepDirection
    monkeypatch.setattr(StepDirection, 'MIN_STEP_FRACTION', 1e-6 / (_config().smoother.nominal_speed * 0.196))


def test_a_first_step_without_parallax_does_not_make_the_window_indeterminate(loop, monkeypatch):
    """A rig that starts off slowly: its first step (0.8 cm at 5.1 Hz) shows no parallax and is stationary, so the
    next frame is predicted at rest and its direction factor linearised at a zero-length step. Unfloored, that made
    the window indeterminate: five anchoring repairs here (a simulated paper loop restarted its graph and stood
    still for 0.6 s, docs/results.md "Stop 52")."""
    first = loop.observations[1]
    still = {side: dataclasses.replace(first.camera(side), flow_curr=first.camera(side).flow_prev)
             for side in ('right', 'left')}
    frames = [loop.observations[0], dataclasses.replace(first, **still), *loop.observations[2:10]]

    def run(**smoother) -> tuple[Smoother, list]:
        sm = Smoother(RIG, _config(**smoother))
        return sm, [sm.update(obs) for obs in frames]

    sm, results = run()
    assert results[1].status is StepStatus.STATIONARY
    assert sm.repairs == 0 and sm.restarts == 0 and all(r.pose.is_finite() for r in results)
    _old_direction_floor(monkeypatch)
    # (stop 55's forward-motion prior and log-space length gauge each keep this window determinate too: the old
    # floor is shown without them; and with every pass made: a window that stops its passes early met the
    # indeterminate linearisation under the default OpenBLAS kernel and missed it under Prescott and Haswell)
    monkeypatch.setattr(Smoother, 'SCALE_GAUGE_SIGMA', 1e9)
    monkeypatch.setattr(FixedLagWindow, 'STEP_TOLERANCE', (0.0, 0.0))
    sm, _ = run(forward_sigma_deg=0.0)
    assert sm.repairs + sm.restarts > 0                    # measured 5 repairs


def _enters(baseline_m: float, scale_observed: bool = True, stood_s_ago: float | None = 1.0) -> bool:
    """Whether a right-camera track seen from five rig poses along z (``baseline_m`` apart end to end) with rays
    turning by 1 deg in all enters the graph; the rig's last stationary step ``stood_s_ago`` (None: never)."""
    from fixego_ros.estimation.factors import to_gtsam
    from fixego_ros.estimation.keys import LandmarkId, pose_key
    from fixego_ros.estimation.smoother import _Update, _View
    from fixego_ros.geometry.rotation import Pose

    sm = Smoother(RIG, _config())
    if scale_observed:
        sm._aids.add('the vergence step')
    if stood_s_ago is not None:
        sm._stood = 0.4 - stood_s_ago
    up, views = _Update(), []
    cam = RIG.cam_to_rig('right', 0.0, 0.0)
    for k, f in enumerate(np.linspace(0.0, 1.0, 5)):
        up.add_value(pose_key(k), to_gtsam(Pose(np.eye(3), np.array([0.0, 0.0, f * baseline_m]))), 0.1 * k)
        ray = Rotation.from_euler('y', f, degrees=True).apply([0.6, 0.0, 1.0])
        views.append(_View(k, 0.1 * k, 'right', ray / np.linalg.norm(ray), cam))
    lid = LandmarkId(LandmarkKind.TRACK, 'right', 7)
    sm._try_landmark(lid, views, up, 0.4)
    return lid in sm._landmarks


def test_a_rig_starting_off_with_its_scale_measured_holds_a_track_to_the_far_guess_baseline():
    """Stop 41. A rig that stood (a stationary step within the lag) and has its scale measured: a track enters only
    once its views span the baseline at which a landmark at the far guess would show the minimum parallax
    (4 m x tan 0.5 deg = 35 mm). The demo's heads settle after the start-up vergence step, the graph drifts
    0.2-0.4 deg, and tracks entered with 0.5-0.75 deg over 10-16 mm at 0.4-1.7 m for 3-4 m; the window went
    indeterminate and the smoother restarted without its scale. Not before the scale is measured, and not for a
    rig that has not stood within the lag: a graph whose scale was just measured may still believe it creeps (the
    bench's walk with vergence: every track kept out, 2.3 -> 197 cm)."""
    assert not _enters(0.02)
    assert _enters(0.05)
    assert _enters(0.02, scale_observed=False)
    assert _enters(0.02, stood_s_ago=None) and _enters(0.02, stood_s_ago=10.0)


def _start_from_rest(loop) -> tuple[Smoother, float, set]:
    rest, moving = _rest_then_move(loop)
    sm, _ = _stand_still(loop, rest)
    at_rest = {lid.kind for lid in sm._landmarks}
    _, est, true = _replay(sm, moving)
    return sm, float(np.linalg.norm(est - true, axis=1).mean()), at_rest


def test_a_rig_that_starts_from_rest_moves_off_as_one_that_never_stood(loop, monkeypatch):
    """Stop 31. Standing still: tracks seen from one place say nothing about their depth and no longer enter the
    graph at the far guess (they did once seen patient_views times, and the first metres then fit wrong depths),
    and the constant-twist prior lets the speed grow from zero (its floor was 0.05 m/s: the path crept). Live demo
    runs that started 30-45 deg off or barely moved for seconds."""
    sm, mean, at_rest = _start_from_rest(loop)
    assert at_rest == {LandmarkKind.FIXATION}           # no track entered at the far guess
    assert mean < 0.3 and sm.restarts == 0              # as without the rest (test above: ~0.19 m)
    monkeypatch.setattr(Smoother, 'TWIST_MIN_SPEED', 0.1)
    _, crept, _ = _start_from_rest(loop)
    assert crept > 0.3                                  # the old floor: ~0.36 m (~0.6 m before stationary steps
                                                        # held the rig still, stop 40)


def test_landmarks_the_window_drops_are_forgotten_and_the_smoother_goes_on(loop, monkeypatch):
    """Stop 40. With every landmark counted as behind its cameras the window drops each one the pass after it
    enters: the smoother forgets their tracks (a later sighting must not attach to a landmark without views), keeps
    going on its steps and priors without a numerical failure, and counts the drops."""
    from fixego_ros.estimation import fixed_lag

    monkeypatch.setattr(fixed_lag.FixedLagWindow, 'MIN_DEPTH_M', 1e3)
    sm = Smoother(RIG, _config())
    kept = []
    for obs in loop.observations:
        r = sm.update(obs)
        kept.append(len(sm._landmarks))
        assert r.pose.is_finite()
    assert sm.dropped > 50 and sm.restarts == 0 and max(kept) == 0


def _restart_at(loop, k_fail: int, monkeypatch) -> tuple[Smoother, np.ndarray, np.ndarray]:
    """The loop with vergence measurements up to frame ``k_fail``, whose update fails numerically (the window
    raises as GTSAM does), so the smoother starts a new graph there; the path as a caller keeps it."""
    from fixego_ros.estimation import fixed_lag

    sm = Smoother(RIG, _config())
    rng = np.random.default_rng(3)
    path: dict[float, np.ndarray] = {}
    last_fid = None
    update = fixed_lag.FixedLagWindow.update

    def fail(self, *args, **kwargs):
        raise RuntimeError('Indeterminant linear system detected while working near variable 1 (test)')

    for k, obs in enumerate(loop.observations):
        monkeypatch.setattr(fixed_lag.FixedLagWindow, 'update', fail if k == k_fail else update)
        r = sm.update(obs)
        if k < k_fail and obs.right.fixation_id != last_fid:
            sm.add_fixation_point(obs.stamp, 'right', *_vergence(loop, k, 0.005, rng))
            last_fid = obs.right.fixation_id
        path[r.stamp] = r.pose.t
        path.update((s, p.t) for s, p in r.revised)
    monkeypatch.setattr(fixed_lag.FixedLagWindow, 'update', update)
    return sm, np.array([path[s] for s in loop.stamps]), np.array([p.t for p in loop.poses])


def test_a_restarted_graph_moves_on_at_the_speed_it_had(loop, monkeypatch):
    """Stop 35. A numerical failure starts a new graph; it used to begin at rest (its first step had a prior of zero
    motion), no landmark then had the parallax to enter and hold the scale, and the graph stayed at rest while the
    rig moved on (a recorded live run: 10 s standing still, 114 cm mean). It now starts with the old graph's
    motion. Here the rig gets no vergence measurement after the failure at frame 30 (6 s in): 0.895 of the true
    length over the next 14 frames under every OpenBLAS kernel.

    Not asserted: what a graph restarted at rest does. It is bistable, and the kernel's last bits pick the branch
    (stop 54, on an AVX-512 machine: 0.76 of the true length with the default kernel and SkylakeX, 0.005 under
    Prescott, 0.03 under Haswell and Zen; with the step direction's floor before stop 52, 0.004, 3e-6 and 0.44). That
    is why a restart carries the old graph's motion."""
    k = 30
    sm, est, true = _restart_at(loop, k, monkeypatch)
    after = slice(k + 1, k + 15)
    ratio = _length(est[after]) / _length(true[after])
    assert sm.restarts == 1 and 0.8 < ratio < 1.0                  # measured 0.895


def _swung(obs: FrameObservation, k: int, rng: np.random.Generator, prev: dict[str, np.ndarray],
           sigma_deg: float) -> FrameObservation:
    """Both heads swinging back, as the front end sees it: every track and the fixation point new at each frame (no
    landmark seen again) and each camera's readings off by ``sigma_deg`` (a fresh error per frame; the flow's
    earlier rays carry the previous frame's)."""
    cams = {}
    for side in ('right', 'left'):
        c = obs.camera(side)
        R = Rotation.from_rotvec(rng.normal(0.0, math.radians(sigma_deg), 3)).as_matrix()
        R_prev, prev[side] = prev.get(side, np.eye(3)), R
        cams[side] = dataclasses.replace(
            c, cam_to_rig=R @ c.cam_to_rig, track_ids=np.asarray(c.track_ids) + 100_000 * (k + 1),
            track_rays=np.asarray(c.track_rays) @ R.T, fixation_id=c.fixation_id + 1000 * (k + 1),
            fixation_ray=None if c.fixation_ray is None else R @ c.fixation_ray,
            flow_prev=np.asarray(c.flow_prev) @ R_prev.T, flow_curr=np.asarray(c.flow_curr) @ R.T)
    return dataclasses.replace(obs, right=cams['right'], left=cams['left'])


def _feed_path(sm: Smoother, frames, loop, rng: np.random.Generator, path: dict[float, np.ndarray]) -> list:
    """Feed ``frames`` (the frame's index in ``loop``, or None for a frame made up, and its observation), with a
    vergence measurement at each new right fixation of a frame of the loop; keeps the path in ``path`` as a caller
    does (each result's pose, then its revisions); the results."""
    results, last_fid = [], None
    for k, obs in frames:
        if k is not None and obs.right.fixation_id != last_fid:
            sm.add_fixation_point(obs.stamp, 'right', *_vergence(loop, k, 0.005, rng))
        last_fid = obs.right.fixation_id
        r = sm.update(obs)
        results.append(r)
        path[r.stamp] = r.pose.t
        path.update((s, p.t) for s, p in r.revised)
    return results


def _gap_length_ratio(loop, gap: range, **smoother) -> float:
    """The loop with vergence measurements, both heads swinging back over the frames of ``gap``: estimated over true
    path length across the gap."""
    noise = np.random.default_rng(13)
    prev: dict[str, np.ndarray] = {}
    frames = [(None, _swung(obs, k, noise, prev, 0.3)) if k in gap else (k, obs)
              for k, obs in enumerate(loop.observations)]
    path: dict[float, np.ndarray] = {}
    _feed_path(Smoother(RIG, _config(**smoother)), frames, loop, np.random.default_rng(3), path)
    est = np.array([path[s] for s in loop.stamps])
    true = np.array([p.t for p in loop.poses])
    span = slice(gap.start, gap.stop + 1)
    return _length(est[span]) / _length(true[span])


def test_frames_no_landmark_places_keep_the_speed_the_landmarks_measured(loop, monkeypatch):
    """Stop 36. In recorded live runs both heads swung back together: for ~1 s the front end's tracks were all new,
    no landmark in the graph was seen, and the speed decayed to zero under the relative constant-twist prior (cheap
    step by step); the graph then failed and restarted at rest. A frame no landmark places now keeps the speed
    measured before (HeldSpeed). Here 4 s (20 frames) of swing-backs with 0.3 deg reading errors."""
    gap = range(25, 45)
    assert 0.6 < _gap_length_ratio(loop, gap) < 1.4                        # measured 0.86
    monkeypatch.setattr(Smoother, '_hold_speed', lambda self, i, stamp, tf, up: None)
    # the forward-motion prior (stop 55) alone also holds it here (0.98): HeldSpeed is shown without it, and without
    # the log-space gauge, which a graph whose landmarks never placed a frame (this stand-in records none) keeps
    monkeypatch.setattr(Smoother, 'SCALE_GAUGE_SIGMA', 1e9)
    # and with the twist prior's rotation held at its floor, as it was before stop 73: the swing-backs' noisy rates
    # loosen it, and this stripped graph then runs 4x long instead of decaying (a failure too, but another one)
    monkeypatch.setattr(Smoother, 'RATE_SPREAD_GAIN', 0.0)
    assert _gap_length_ratio(loop, gap, forward_sigma_deg=0.0) < 0.5       # measured 0.21: the speed decays


def _blind_gap(loop, gap: range) -> tuple[list, np.ndarray, np.ndarray]:
    """The loop with vergence measurements; over ``gap`` both heads swing back with neither fixation valid (as
    camera_node publishes it: id -1), every track new and the readings off by 1 deg per frame. The gap's results,
    and the estimated (revised) and true positions of all frames."""
    sm = Smoother(RIG, _config())
    rng, noise = np.random.default_rng(3), np.random.default_rng(13)
    prev: dict[str, np.ndarray] = {}
    path: dict[float, np.ndarray] = {}
    last_fid, in_gap = None, []
    for k, obs in enumerate(loop.observations):
        if k in gap:
            obs = _swung(obs, k, noise, prev, 1.0)
            obs = dataclasses.replace(obs, right=dataclasses.replace(obs.right, fixation_ray=None, fixation_id=-1),
                                      left=dataclasses.replace(obs.left, fixation_ray=None, fixation_id=-1))
        elif obs.right.fixation_id != last_fid:
            sm.add_fixation_point(obs.stamp, 'right', *_vergence(loop, k, 0.005, rng))
            last_fid = obs.right.fixation_id
        r = sm.update(obs)
        if k in gap:
            in_gap.append(r)
        path[r.stamp] = r.pose.t
        path.update((s, p.t) for s, p in r.revised)
    return in_gap, np.array([path[s] for s in loop.stamps]), np.array([p.t for p in loop.poses])


def test_frames_without_either_fixation_are_placed_by_the_motion_prior(loop, monkeypatch):
    """Stop 42. When both heads swing back at once neither camera publishes a fixation, the readings of heads turning
    80 deg/s are off and every track is new; the two-frame steps and sightings of such frames turned the rig 3.5 deg/s
    too fast for seconds after (stop 38's recorded bag, replayed with its own fixations: 47.9 cm mean, now 4.4 cm).
    Such frames are placed by the motion prior (the speed held from before): no step, no sighting. Here 1 s (5 frames)
    of swing-back with 1 deg reading errors."""
    gap = range(25, 30)
    in_gap, est, true = _blind_gap(loop, gap)
    assert all(r.status is StepStatus.PREDICTED and r.twoframe is None for r in in_gap)
    assert all('no fixation in either camera' in r.message for r in in_gap)
    span = slice(gap.start - 1, gap.stop + 1)
    assert 0.7 < _length(est[span]) / _length(true[span]) < 1.3        # the speed went on across the gap
    monkeypatch.setattr(Smoother, '_blind', staticmethod(lambda fix: False))
    in_gap, _, _ = _blind_gap(loop, gap)
    assert any(r.status is not StepStatus.PREDICTED for r in in_gap)     # without the rule the rays placed them


def test_a_measurement_whose_frame_a_restart_dropped_moves_to_the_new_graph(loop):
    """A live demo: the smoother restarted at rest just before the start-up vergence measurement arrived; its frame
    was in the failed graph, so it was ignored ("left the lag") and the whole run had no scale (31 cm mean). It is
    moved to the new graph's next frame with the camera's fixation (both graphs share one world frame)."""
    obs = loop.observations
    sm = Smoother(RIG, _config())
    for o in obs[:6]:
        sm.update(o)
    sm._restart()                                   # as a numerical failure does
    for o in obs[6:8]:
        sm.update(o)
    assert obs[6].right.fixation_id == obs[5].right.fixation_id
    rng = np.random.default_rng(0)
    sm.add_fixation_point(obs[5].stamp, 'right', *_vergence(loop, 5, 0.0, rng))
    assert sm.scale_observed and 'ignored' not in sm.scale_note(), sm.scale_note()
    assert sm.vergence_used == 1
    stamp, rel_std = sm.scale_measurement
    assert stamp == obs[6].stamp and 0.0 < rel_std < 0.05     # carried one frame (0.2 s at rest-like speed)


def test_marginals_only_change_the_covariance(loop):
    """Replay runs the smoother without the newest pose's marginal (it writes poses only): the trajectory is the
    same to the bit, and the covariance is the unknown one instead of the smoother's marginal."""
    with_marginals, est, _ = _replay(Smoother(RIG, _config()), loop)
    without, est_without, _ = _replay(Smoother(RIG, _config(), marginals=False), loop)
    assert np.array_equal(est, est_without)
    assert all(np.array_equal(a.pose.t, b.pose.t) for a, b in zip(with_marginals, without, strict=True))
    assert np.allclose(without[-1].pose_covariance[:3, :3], np.eye(3) * 1e-2)      # rotation unknown (0.1 rad)
    assert with_marginals[-1].pose_covariance[0, 0] < 1e-3      # the marginal: the rotation is well known


def test_the_marginal_is_computed_at_most_once_per_period_and_turned_with_the_frame(loop, monkeypatch):
    """The newest pose's marginal costs ~10 ms of a live update: computed for a frame at most once per
    ``MARGINAL_PERIOD_S`` of stamps; the frames in between carry it turned into their own orientation."""
    from fixego_ros.estimation.fixed_lag import FixedLagWindow
    from fixego_ros.estimation.keys import pose_key
    computed: list[int] = []
    real = FixedLagWindow.marginal_covariance
    monkeypatch.setattr(FixedLagWindow, 'marginal_covariance',
                        lambda self, key: computed.append(key) or real(self, key))
    results, _, _ = _replay(Smoother(RIG, _config()), loop)
    span = loop.stamps[-1] - loop.stamps[0]
    assert 1 < len(computed) <= span / Smoother.MARGINAL_PERIOD_S + 2 < len(results) - 1
    fresh = {r.index for r in results if pose_key(r.index) in computed}
    shared = 0
    for a, b in itertools.pairwise(results):
        if b.index in fresh or a.pose_covariance[0, 0] >= 1e-2:
            continue
        turned = b.pose.R @ a.pose.R.T
        np.testing.assert_allclose(b.pose_covariance[:3, :3], turned @ a.pose_covariance[:3, :3] @ turned.T,
                                   atol=1e-15)
        shared += 1
    assert shared >= len(results) // 3


def _move_then_stop(loop, k_stop: int, n_rest: int, **smoother) -> tuple[np.ndarray, np.ndarray]:
    """The loop with vergence measurements up to frame ``k_stop``, where the rig stops and stands ``n_rest`` frames
    (:meth:`LandmarkRun.standing`). The estimated (revised) positions at the stop and at each frame standing."""
    standing = loop.standing(k_stop, n_rest)
    frames = [*enumerate(loop.observations[:k_stop + 1]), *((None, obs) for obs in standing)]
    path: dict[float, np.ndarray] = {}
    results = _feed_path(Smoother(RIG, _config(**smoother)), frames, loop, np.random.default_rng(3), path)
    assert all(r.status is StepStatus.STATIONARY for r in results[k_stop + 2:])
    return path[loop.stamps[k_stop]], np.array([path[o.stamp] for o in standing])


def test_a_rig_that_stops_where_no_landmark_places_its_frames_stands_still(loop, monkeypatch):
    """Stop 61. A rig that stops while both heads take new points: no landmark places the frames, and they kept the
    speed the landmarks last measured (HeldSpeed) although the rays saw no parallax; the stationary step, its length
    sigma inflated tenfold once a scale aid measured the scale, did not hold them. A live demo whose rig stood 2 s
    after the loop ran on by 30 cm. A stationary step now holds the frame still at the nominal scale's sigma and
    gets no held speed."""
    at_stop, standing = _move_then_stop(loop, 40, 10)
    assert np.linalg.norm(standing - at_stop, axis=1).max() < 0.05     # measured 0.024 (0.37 before)
    monkeypatch.setattr(TwoFrameStep, 'factor', _old_stationary_step)
    monkeypatch.setattr(Smoother, '_hold_speed', _held_even_at_rest)
    at_stop, standing = _move_then_stop(loop, 40, 10)
    assert np.linalg.norm(standing[-1] - at_stop) > 0.2          # ran on at the speed it had


_NEW_STEP_FACTOR = TwoFrameStep.factor
_NEW_HOLD_SPEED = Smoother._hold_speed


def _old_stationary_step(self, ref, frame, step, covariance, dt, measured=False):
    """Before stop 61: the stationary step's length sigma inflated like a moving one's once the scale is measured."""
    if np.any(step.t) or not measured:
        return _NEW_STEP_FACTOR(self, ref, frame, step, covariance, dt, measured)
    return _NEW_STEP_FACTOR(self, ref, frame, step, covariance, dt * self.AIDED_LENGTH_SIGMA, measured)


def _held_even_at_rest(self, i, stamp, tf, up):
    return _NEW_HOLD_SPEED(self, i, stamp, False, up)


def test_a_stationary_step_holds_the_frame_only_over_a_long_enough_interval():
    """Stop 63. A step of 10-40 ms cannot tell rest from slow motion (at 0.2 m/s it moves 2-8 mm, which a narrow field
    of view shows mostly as a rotation); held as a stand, such steps stood a demo's rig on its last 0.2 m/s stretch.
    Over at least STATIONARY_MIN_S the stand holds the frame at STATIONARY_LENGTH_SIGMA nominal steps; below, the step
    claims no length beyond a moving step's, and the smoother counts it neither as a stand nor as motion."""
    from fixego_ros.geometry.rotation import Pose
    steps = TwoFrameStep(1e-3, 0.5, 1.0)
    dt_short, dt_long = 0.5 * TwoFrameStep.STATIONARY_MIN_S, 2.0 * TwoFrameStep.STATIONARY_MIN_S

    def length_sigma(dt: float, step: Pose) -> float:
        return float(np.sqrt(steps.factor(0, 1, step, np.eye(6) * 1e-6, dt, measured=True)
                             .noiseModel().noise().covariance()[3, 3]))

    moving = Pose(np.eye(3), np.array([0.0, 0.0, 1.0]))
    assert length_sigma(dt_long, Pose.identity()) == pytest.approx(0.5 * dt_long * TwoFrameStep.STATIONARY_LENGTH_SIGMA)
    assert length_sigma(dt_short, Pose.identity()) == pytest.approx(length_sigma(dt_short, moving))
    assert length_sigma(dt_short, moving) == pytest.approx(0.5 * dt_short * TwoFrameStep.AIDED_LENGTH_SIGMA)
    assert TwoFrameStep.stands(StepStatus.STATIONARY, dt_long)
    assert not TwoFrameStep.stands(StepStatus.STATIONARY, dt_short)
    assert not TwoFrameStep.stands(StepStatus.OK, dt_long)


def _turn_error_deg(run, results, k: int) -> float:
    """How far the pose published for frame ``k`` (as placed, before any revision) is turned from the truth."""
    rel = (run.poses[0].inverse() @ run.poses[k]).R
    return math.degrees(np.linalg.norm(Rotation.from_matrix(rel.T @ results[k].pose.R).as_rotvec()))


def _sightings_used(monkeypatch) -> dict[int, int]:
    """Each frame's landmark observations that passed the projection gate into the graph, by frame index."""
    used: dict[int, int] = {}
    solve = Smoother._solve

    def counted(self, up):
        used[self._index] = up.observations
        return solve(self, up)

    monkeypatch.setattr(Smoother, '_solve', counted)
    return used


@pytest.mark.parametrize('check', [True, False])
def test_a_resection_both_the_prediction_and_the_two_frame_step_contradict_is_not_used(loop, monkeypatch, check):
    """Stop 72. On the arc (frame 45, the rig turning ~5 deg a frame) the resection turns 15 deg too far. The
    prediction and the two-frame step both disagree with it, so the frame is placed at the step's rotation: its
    sightings pass the projection gate as they do unperturbed, the rejection is counted and said, and the frame ends
    within a degree of the truth. Control: with the check off the frame is gated against the wrong pose and loses
    its sightings. (Unperturbed, frame 45's resection is kept.)"""
    used = _sightings_used(monkeypatch)
    clean = Smoother(RIG, _config())
    assert 'resection' not in _replay(clean, loop)[0][45].message
    seen = used[45]
    if not check:
        monkeypatch.setattr(Smoother, 'RESECTION_AGREEMENT_DEG', math.inf)
    perturb_resection(monkeypatch, 45, 15.0)
    sm = Smoother(RIG, _config())
    results = _replay(sm, loop)[0]
    assert seen >= 10
    if check:
        assert sm.resections_rejected > clean.resections_rejected and 'resection' in results[45].message
        assert used[45] >= 0.8 * seen and _turn_error_deg(loop, results, 45) < 1.0
    else:
        assert sm.resections_rejected == 0 and used[45] <= 0.2 * seen
