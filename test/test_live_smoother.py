"""The node's back end: the smoother in a child process, a two-frame pose for every frame at once."""

from __future__ import annotations

import dataclasses
import math
import os
import signal
from collections import deque

import numpy as np
import pytest
from conftest import perturb_resection

from fixego_ros.estimation.backend import make_backend
from fixego_ros.estimation.config import EstimatorConfig
from fixego_ros.estimation.frames import FrameObservation
from fixego_ros.estimation.live_smoother import LiveSmoother, Message, _Gate, _Server
from fixego_ros.estimation.smoother import Smoother
from fixego_ros.estimation.stage_times import Stage
from fixego_ros.estimation.status import StepStatus
from fixego_ros.estimation.twoframe import SolverConfig
from fixego_ros.experiments.landmark_scene import LandmarkScene, LandmarkSceneConfig
from fixego_ros.geometry.rig import make_rig
from fixego_ros.sim.trajectories import make_trajectory

RIG = make_rig(640, 480, 21.0, 0.2)
F = RIG.camera('right').fx
WAIT_S = 60.0        # bound on waiting for the child (it answers in well under a second per frame)


@pytest.fixture(scope='module')
def loop():
    """8 s of the papers' loop at 5.1 Hz, 0.3 px noise."""
    scene = LandmarkScene(RIG, LandmarkSceneConfig(noise_px=0.3, max_tracks=40))
    return scene.run(make_trajectory('paper'), duration=8.0)


@pytest.fixture
def live():
    sm = LiveSmoother(RIG, EstimatorConfig(solver=SolverConfig(sigma=1.0 / F)))
    yield sm
    sm.close()


def _vergence(run, k: int):
    p = run.fixation_points[k]['right']
    d = float(np.linalg.norm(p))
    return p, np.eye(3) * (1e-3 * d) ** 2


def _feed(backend, run, wait: bool, speed_from_s: float | None = None):
    """Every frame, with a vergence point at each new right fixation (or, given ``speed_from_s``, the true velocity from
    then on instead); the path as the node keeps it (stretched by each result's ``prefix_scale``, then its pose and its
    revisions). ``wait``: let the child answer each frame before the next (no frame skipped)."""
    path, results, last_fid = {}, [], None
    for k, obs in enumerate(run.observations):
        if speed_from_s is not None and obs.stamp - run.stamps[0] >= speed_from_s:
            step = run.poses[k - 1].inverse() @ run.poses[k]
            backend.add_velocity(obs.stamp - 1e-3, step.t / (obs.stamp - run.stamps[k - 1]), np.eye(3) * 1e-4)
        r = backend.update(obs)
        if speed_from_s is None and obs.right.fixation_id != last_fid:
            backend.add_fixation_point(obs.stamp, 'right', *_vergence(run, k))
            last_fid = obs.right.fixation_id
        results.append(r)
        path = {s: p * r.prefix_scale for s, p in path.items()}
        path[r.stamp] = r.pose.t
        path.update({s: p.t for s, p in r.revised})
        if wait and isinstance(backend, LiveSmoother):
            path.update({s: p.t for s, p in backend.drain(WAIT_S)})
    if isinstance(backend, LiveSmoother):
        path.update({s: p.t for s, p in backend.drain(WAIT_S)})
    return results, np.array([path[s] for s in run.stamps])


def test_the_path_is_the_in_process_smoothers(loop, live):
    """The child runs the same smoother on the same messages in the same order: its path is the in-process one."""
    _, expected = _feed(Smoother(RIG, EstimatorConfig(solver=SolverConfig(sigma=1.0 / F))), loop, wait=False)
    results, path = _feed(live, loop, wait=True)
    assert np.max(np.abs(path - expected)) < 1e-9
    assert live.frames_skipped == 0 and live.smoothed_results == len(loop.observations)
    assert results[-1].scale_observed and 'vergence' in results[-1].scale_note
    # the child's own time for each frame it answered (/diagnostics smoother_update_ms): one each, positive
    assert len(live.update_ms) == len(loop.observations) and all(0.0 < ms < 1e3 * WAIT_S for ms in live.update_ms)
    # ... by stage (/diagnostics smoother_<stage>_ms): every stage has one sample per answer, the passes always run,
    # and the stages add up to no more than the update they belong to
    assert {k: len(v) for k, v in live.stage_ms.items()} == {s.value: len(loop.observations) for s in Stage}
    assert all(ms > 0.0 for s in (Stage.LINEARISE, Stage.ELIMINATE, Stage.SOLVE) for ms in live.stage_ms[s.value])
    totals = np.sum([list(v) for v in live.stage_ms.values()], axis=0)
    assert np.all(totals <= np.array(live.update_ms) + 1e-6)
    assert {k: len(v) for k, v in live.stage_samples(3).items()} == {s.value: 3 for s in Stage}


def test_the_first_measurements_stretch_reaches_the_caller_as_in_process(loop):
    """A speed source that starts 4 s in, nominal speed 1 m/s against the rig's ~0.3: the child's stretch of the path
    built before it (Smoother._stretch) reaches the caller once, and the path it keeps is the in-process one."""
    config = EstimatorConfig(solver=SolverConfig(sigma=1.0 / F))
    config = dataclasses.replace(config, smoother=dataclasses.replace(config.smoother, nominal_speed=1.0))
    expected_results, expected = _feed(Smoother(RIG, config), loop, wait=False, speed_from_s=4.0)
    live = LiveSmoother(RIG, config)
    try:
        results, path = _feed(live, loop, wait=True, speed_from_s=4.0)
    finally:
        live.close()
    scales = [r.prefix_scale for r in results if r.prefix_scale != 1.0]
    assert len(scales) == 1 and scales == [r.prefix_scale for r in expected_results if r.prefix_scale != 1.0]
    assert scales[0] < 0.8
    assert np.max(np.abs(path - expected)) < 1e-9


def test_every_frame_gets_a_pose_at_once_and_it_follows_the_smoother(loop, live):
    """Fast poses: the smoother's motion carried to the stamp once it has answered (it answers every frame here).
    Once the scale is measured they stay close to the truth (generous bound; the path is the refined answer)."""
    results, _ = _feed(live, loop, wait=True)
    assert results[0].status is StepStatus.INIT
    assert all(r.placed and r.pose.is_finite() and np.all(np.isfinite(r.pose_covariance)) for r in results)
    assert sum(r.status is StepStatus.CARRIED for r in results) >= len(results) - 3    # once the smoother answered
    true = np.array([p.t for p in loop.poses])
    fast = np.array([r.pose.t for r in results])
    aided = [k for k, r in enumerate(results) if r.scale_observed]
    assert len(aided) > len(results) // 2
    assert np.linalg.norm(fast[aided] - true[aided], axis=1).mean() < 0.3


def test_a_busy_smoother_skips_non_keyframes_but_never_a_keyframe(loop, live):
    """Frames sent faster than the child solves: it takes every keyframe (later flow starts there) and, of the other
    frames, what the gate admits; every frame still gets a pose, and the skipped ones move with the frame their flow
    starts from when the smoother revises it (the path has no fast poses left among smoothed ones)."""
    observations = [dataclasses.replace(o, keyframe=(k % 4 == 0)) for k, o in enumerate(loop.observations)]
    results = [live.update(o) for o in observations]
    revised = dict(live.drain(WAIT_S))
    assert all(r.pose.is_finite() for r in results)
    assert live.smoothed_results + live.frames_skipped == len(observations)
    keyframes = {o.stamp for o in observations if o.keyframe}
    assert keyframes <= set(revised)
    assert set(revised) == {o.stamp for o in observations}


def test_a_smoother_far_behind_still_revises_every_frame_of_the_path(loop, live, monkeypatch):
    """Frames stay while the smoother may still revise them, beyond ``HISTORY_S``: here the child is stopped while
    the whole run is sent (it is then seconds of stamps behind, as a demo's child on a busy machine, 7-14 s), and
    its answers afterwards still reach every frame of the path."""
    monkeypatch.setattr(LiveSmoother, 'HISTORY_S', 1.0)
    observations = [dataclasses.replace(o, keyframe=(k % 4 == 0)) for k, o in enumerate(loop.observations)]
    os.kill(live._process.pid, signal.SIGSTOP)
    try:
        results = [live.update(o) for o in observations]
    finally:
        os.kill(live._process.pid, signal.SIGCONT)
    assert not any(r.revised for r in results)
    revised = dict(live.drain(WAIT_S))
    assert set(revised) == {o.stamp for o in observations}
    assert live.smoothed_results + live.frames_skipped == len(observations)
    monkeypatch.setattr(LiveSmoother, 'MAX_HISTORY_S', 1.0)      # the bound holds: a stalled child keeps no more
    live.reset()
    for o in observations:
        live.update(o)
    assert live._recent[-1].stamp - live._recent[0].stamp <= 1.0


def test_behind_says_how_far_the_smoothers_newest_result_lags_the_newest_frame(loop, live):
    """``behind_s`` (on /diagnostics): 0 while the child answers every frame; once it stops answering, the stamps
    sent since its last result."""
    assert live.behind_s == 0.0
    for obs in loop.observations[:2]:
        live.update(obs)
        live.drain(WAIT_S)
    assert live.behind_s == 0.0
    live._process.kill()
    live._process.join(WAIT_S)
    for obs in loop.observations[2:5]:
        live.update(obs)
    assert live.behind_s == pytest.approx(loop.stamps[4] - loop.stamps[1])


def test_wait_for_answer_says_when_the_child_has_sent_something_and_is_false_once_it_is_gone(loop, live):
    """What the node's waiter thread polls: True once the child has answered a frame, False after the answer was
    taken, when the child is dead, and always inline (its answers come with each frame)."""
    assert not live.wait_for_answer(0.0)
    live.update(loop.observations[0])
    assert live.wait_for_answer(WAIT_S)
    live.drain(0.0)
    assert not live.wait_for_answer(0.0)
    live._process.kill()
    live._process.join(WAIT_S)
    live.update(loop.observations[1])
    assert not live.wait_for_answer(0.5)
    inline = LiveSmoother(RIG, live.config, inline=True)
    inline.update(loop.observations[0])
    assert not inline.wait_for_answer(0.5)


def test_bad_aids_are_refused_here_and_a_dead_child_leaves_poses_flowing(loop, live):
    with pytest.raises(ValueError):
        live.add_velocity(1.0, np.array([np.nan, 0.0, 0.0]), np.eye(3))
    with pytest.raises(ValueError):
        live.add_fixation_point(1.0, 'middle', np.ones(3), np.eye(3))
    live.update(loop.observations[0])
    live._process.kill()
    live._process.join(WAIT_S)
    assert not live.alive
    r = live.update(loop.observations[1])
    assert r.placed and r.pose.is_finite()
    assert live.drain(1.0) == ()
    live.close()
    live.close()


def test_the_factory_puts_the_smoother_in_a_child_only_when_live():
    config = EstimatorConfig()
    inline = make_backend(RIG, config)
    assert isinstance(inline, LiveSmoother) and inline._process is None and inline.alive
    backend = make_backend(RIG, config, live=True)
    try:
        assert isinstance(backend, LiveSmoother) and backend.alive
    finally:
        backend.close()
    assert not backend.alive


def test_inline_the_smoother_takes_the_child_path_on_keyframes_and_is_deterministic(loop):
    """Replay's back end: the same class with the smoother in this process. With every frame a keyframe its path is
    the child's when the child answers every frame; with keyframes every 4th frame it takes those and, between
    them, a frame once ``MIN_GAP_S`` has passed since the last one it took, and two runs give the same bytes (the
    flow here starts from the previous frame, so the skipped frames break its chain: no accuracy is asserted)."""
    config = EstimatorConfig(solver=SolverConfig(sigma=1.0 / F))
    _, expected = _feed(Smoother(RIG, config), loop, wait=False)
    _, path = _feed(LiveSmoother(RIG, config, inline=True), loop, wait=False)
    assert np.max(np.abs(path - expected)) < 1e-9

    observations = [dataclasses.replace(o, keyframe=(k % 4 == 0)) for k, o in enumerate(loop.observations)]
    sparse = dataclasses.replace(loop, observations=observations)
    runs = []
    for _ in range(2):
        inline = LiveSmoother(RIG, config, inline=True)
        inline._conn.gate.min_gap_s = 0.5           # > the 0.2 s frame period: some non-keyframes stay out
        results, path = _feed(inline, sparse, wait=False)
        runs.append(path)
        assert all(r.placed and r.pose.is_finite() for r in results)
        assert inline.frames_skipped > 0
        assert inline.smoothed_results + inline.frames_skipped == len(observations)
    assert np.array_equal(runs[0], runs[1])


@pytest.mark.parametrize('point_first', [True, False], ids=['point-before-frame', 'point-after-frame'])
def test_inline_the_frame_of_each_vergence_measurement_goes_into_the_graph(loop, point_first):
    """A measurement names the right fixation point at its frame's stamp. Carried to a neighbouring frame at the
    nominal scale (before the first one) it can miss that frame's fixation ray and be refused: the 30 Hz walk with a
    0.2 s gap went without a scale for 1.6 s. So its frame goes in, whether the measurement comes before it (replay
    reads it first) or right after it; every measurement here lands on a frame that the gap alone leaves out."""
    config = EstimatorConfig(solver=SolverConfig(sigma=1.0 / F))
    observations = [dataclasses.replace(o, keyframe=(k % 4 == 0)) for k, o in enumerate(loop.observations)]
    inline = LiveSmoother(RIG, config, inline=True)
    inline._conn.gate.min_gap_s = 0.5           # > the 0.2 s frame period: frame 4k + 2 stays out without its point
    measured = [k for k in range(len(observations)) if k % 4 == 2][:5]
    for k, obs in enumerate(observations):
        if point_first and k in measured:
            inline.add_fixation_point(obs.stamp, 'right', *_vergence(loop, k))
        inline.update(obs)
        if not point_first and k in measured:
            inline.add_fixation_point(obs.stamp, 'right', *_vergence(loop, k))
    smoother = inline._conn._server.smoother
    assert smoother.vergence_used == len(measured), smoother.scale_note()
    assert {observations[k].stamp for k in measured} <= {f.stamp for f in smoother._frames}
    inline.drain(WAIT_S)
    assert inline.smoothed_results + inline.frames_skipped == len(observations)
    assert inline.vergence_used == len(measured)        # what the node reports on /diagnostics
    left_out = LiveSmoother(RIG, config, inline=True)       # the control: without their points they stay out
    left_out._conn.gate.min_gap_s = 0.5
    for obs in observations[:measured[-1] + 1]:
        left_out.update(obs)
    assert left_out.frames_skipped >= len(measured)
    assert not any(f.stamp in {observations[k].stamp for k in measured}
                   for f in left_out._conn._server.smoother._frames)


def test_a_skipped_frame_between_two_smoothed_ones_lies_between_them():
    """Stop 36: a frame the child skipped rode on its reference with the fast pose's step, so each keyframe's revision
    left a jump at the next one and the refined path was a sawtooth (a demo's 6.9 m for the 5.0 m loop). Once the
    frames on both sides are smoothed it goes on the geodesic between them, and out as a revision."""
    from fixego_ros.estimation.live_smoother import _Recent
    from fixego_ros.geometry.rotation import Pose

    live = LiveSmoother.__new__(LiveSmoother)          # the parent's bookkeeping only: no child process
    live._revised = {}
    a = _Recent(0.0, Pose(np.eye(3), np.zeros(3)), Pose.identity(), {}, smoothed=True)
    skipped = _Recent(0.1, Pose(np.eye(3), np.array([0.0, 0.0, 0.5])), Pose.identity(), {}, ref=a,
                      step=Pose(np.eye(3), np.array([0.0, 0.0, 0.5])))
    b = _Recent(0.4, Pose(np.eye(3), np.array([0.0, 0.0, 0.4])), Pose.identity(), {}, smoothed=True)
    later = _Recent(0.5, Pose(np.eye(3), np.array([0.0, 0.0, 0.9])), Pose.identity(), {}, ref=b)
    live._recent = deque([a, skipped, b, later])
    live._between_smoothed({id(b)})
    np.testing.assert_allclose(skipped.pose.t, [0.0, 0.0, 0.1], atol=1e-12)
    assert set(live._revised) == {0.1}
    np.testing.assert_allclose(later.pose.t, [0.0, 0.0, 0.9])      # after the newest smoothed frame: unchanged


class _Silent:
    """A smoother process that has not answered yet (live, it runs 70-130 ms per frame behind the poses)."""

    closed = False

    def send(self, message) -> None:
        pass

    def poll(self, timeout: float = 0.0) -> bool:
        return False

    def close(self) -> None:
        self.closed = True


def test_with_no_answer_from_the_smoother_the_fast_poses_still_follow_the_motion(loop):
    """Stop 44's cascade: the warm start came from the constant-twist prediction, which stands still until the
    smoother answers (and after any failed frame, whose pose is that prediction); started at zero translation the
    solve lands behind the cameras, so in a demo run 629 of ~800 moving frames failed and the live pose stood
    still. Now the warm start takes the direction of the previous frame's own step (or the last solved heading),
    and a failed one tries the closed-form starts: with no answer at all, every step is solved and the fast
    poses move the way the rig does (at the nominal speed: no scale yet; a generous bound on the direction: these
    5 Hz steps of 4 cm are weakly observed, a cold solve of each lands 30-40 deg off too)."""
    live = LiveSmoother(RIG, EstimatorConfig(solver=SolverConfig(sigma=1.0 / F)), inline=True)
    live._conn = _Silent()
    results = [live.update(o) for o in loop.observations]
    assert live.smoothed_results == 0
    assert all(r.status.usable for r in results[1:])
    steps = np.array([r.step.t for r in results[1:]])             # each frame's step from the one before
    true = np.array([(a.inverse() @ b).t for a, b in zip(loop.poses, loop.poses[1:], strict=False)])
    cosine = np.sum(steps * true, axis=1) / (np.linalg.norm(steps, axis=1) * np.linalg.norm(true, axis=1))
    assert np.median(cosine) > 0.7
    nominal = live.config.smoother.nominal_speed * np.diff(loop.stamps)
    np.testing.assert_allclose(np.linalg.norm(steps, axis=1), nominal, rtol=1e-6)


def test_a_solved_step_without_translation_leaves_the_warm_start_finite(loop):
    """A usable, non-stationary solve whose translation is zero has no direction: it must not become the heading
    the next warm starts take (dividing by its zero length made the heading NaN, and every warm start after it NaN,
    until the next solved step; seen as a RuntimeWarning in make bench)."""
    import warnings

    from fixego_ros.geometry.rotation import Pose
    live = LiveSmoother(RIG, EstimatorConfig(solver=SolverConfig(sigma=1.0 / F)), inline=True)
    live._conn = _Silent()
    real = live.solver.solve
    calls = {'n': 0}

    def zero_on_the_fourth(pairs, **kwargs):
        result = real(pairs, **kwargs)
        calls['n'] += 1
        if calls['n'] == 4:
            result = dataclasses.replace(result, pose=Pose(result.pose.R, np.zeros(3)), status=StepStatus.WEAK)
        return result

    live.solver.solve = zero_on_the_fourth
    with warnings.catch_warnings():
        warnings.simplefilter('error', RuntimeWarning)
        results = [live.update(o) for o in loop.observations[:12]]
    assert calls['n'] >= 5
    assert live._heading is not None and np.all(np.isfinite(live._heading))
    assert all(r.pose.is_finite() for r in results)


def test_once_the_smoother_answers_a_frame_is_dead_reckoned_on_its_velocity_in_the_rig_frame():
    """The live pose's cheap path (~1 ms, no solve): the translation is the smoother's newest velocity in the rig's
    own frame over the time since the keyframe, turned by half the step's rotation; the rotation is what the rays
    give with that translation (Kabsch's fit, corrected for the near points' parallax). On an arc that velocity
    points along the rig's heading whichever way the rig faces. With the smoother's newest frame over
    ``MAX_CARRY_S`` old the rotation comes from the solve, the translation still from that velocity however far the
    smoother lags; too few rays for a rotation leave the frame to the solve."""
    from fixego_ros.estimation.coplanarity import RayPairs
    from fixego_ros.estimation.live_smoother import _Recent
    from fixego_ros.estimation.twoframe import TwoFrameSolver, kabsch_rotation
    from fixego_ros.geometry.rotation import Pose, exp_so3, rot_y, rotation_angle

    live = LiveSmoother.__new__(LiveSmoother)          # the parent's bookkeeping only: no child process
    live.solver = TwoFrameSolver(SolverConfig(sigma=1.0 / F))
    # the smoother's newest motion: 0.2 s along an arc of the rig's heading (z forward, turning about y)
    turn = 0.1
    a = _Recent(0.0, Pose(rot_y(1.0), np.zeros(3)), Pose.identity(), {}, smoothed=True)
    chord = rot_y(1.0 + turn / 2) @ np.array([0.0, 0.0, 0.04])       # 0.2 m/s along the mean heading
    b = _Recent(0.2, Pose(rot_y(1.0 + turn), chord), Pose.identity(), {}, smoothed=True)
    ref = _Recent(0.3, Pose(rot_y(2.5), np.array([1.0, 0.0, 0.0])), Pose.identity(), {}, ref=b)   # facing elsewhere
    live._recent = deque([a, b, ref])
    np.testing.assert_allclose(LiveSmoother._body_velocity(a, b), [0.0, 0.0, 0.2], atol=1e-12)
    R = exp_so3(np.array([0.0, 0.02, 0.0]))
    half = exp_so3(np.array([0.0, 0.01, 0.0]))
    rays = np.random.default_rng(0).normal(size=(30, 3)) + [0.0, 0.0, 4.0]
    pairs = RayPairs.build([(rays, rays @ R, np.zeros(3), 1.0)])        # b = R^T a: a pure rotation R
    pairs_rays = kabsch_rotation(pairs.a, pairs.b)
    carried = live._carried(ref, pairs, pairs_rays, 0.4)
    assert carried.status is StepStatus.CARRIED and carried.status.usable
    np.testing.assert_allclose(carried.pose.R, R, atol=1e-9)
    np.testing.assert_allclose(carried.pose.t, half @ [0.0, 0.0, 0.02], atol=1e-9)
    assert live._carried(ref, pairs, pairs_rays, 0.2 + LiveSmoother.MAX_CARRY_S + 0.01) is None     # lagging: solved
    # points 0.8-1.5 m away, all to one side: over the carried 2 cm forward their parallax leans one way, and
    # Kabsch takes it for rotation
    near = np.random.default_rng(1).uniform([0.3, -0.5, 0.8], [1.5, 0.5, 1.5], size=(60, 3))
    moved = (near - carried.pose.t) @ R                 # the same points after the carried step
    parallax = RayPairs.build([(near, moved, np.zeros(3), 1.0)])
    kabsch = live._dead_reckoned(live._smoothed_span(), kabsch_rotation(parallax.a, parallax.b), 0.1)
    assert rotation_angle(kabsch.R @ R.T) > math.radians(0.1)        # (measured: 0.44 deg; carried 0.0004)
    read = live._carried(ref, parallax, kabsch_rotation(parallax.a, parallax.b), 0.4)
    assert rotation_angle(read.pose.R @ R.T) < 0.1 * rotation_angle(kabsch.R @ R.T)
    late = live._dead_reckoned(live._smoothed_span(), R, 5.0)     # 5 s on the smoother's velocity: 1 m forward
    np.testing.assert_allclose(late.R, R, atol=1e-12)
    np.testing.assert_allclose(late.t, half @ [0.0, 0.0, 1.0], atol=1e-9)
    few = RayPairs.build([(rays[:5], rays[:5] @ R, np.zeros(3), 1.0)])
    assert live._carried(ref, few, kabsch_rotation(few.a, few.b), 0.4) is None
    live._recent = deque([ref])                         # before the smoother has a motion: nothing to reckon on
    assert live._smoothed_span() is None and live._dead_reckoned(None, R, 0.1) is None


def test_the_published_pose_takes_up_a_revision_without_a_jump_and_converges_on_the_estimate():
    """REP-105's odom frame is continuous: when the smoother revises the previous frame (its keyframe moved 5 cm),
    the pose to publish (``odom``) moves on from where it was by the frame's own motion, and closes the gap to the
    estimate (``pose``) by a share ``dt / ODOM_CONVERGENCE_S`` per frame."""
    from fixego_ros.estimation.live_smoother import _Recent
    from fixego_ros.geometry.rotation import Pose

    live = LiveSmoother.__new__(LiveSmoother)          # the parent's bookkeeping only: no child process
    live._odom = None
    frames = [_Recent(0.1 * k, Pose(np.eye(3), np.array([0.01 * k, 0.0, 0.0])), Pose.identity(), {}) for k in (0, 1)]
    live._recent = deque(frames[:1])
    np.testing.assert_allclose(live._odom_pose(frames[0].pose, 0.0).t, 0.0, atol=1e-12)
    live._recent.append(frames[1])
    first = live._odom_pose(frames[1].pose, 0.1)
    np.testing.assert_allclose(first.t, [0.01, 0.0, 0.0], atol=1e-12)       # nothing revised: the estimate
    frames[1].pose = Pose(np.eye(3), np.array([0.06, 0.0, 0.0]))             # the smoother moved it 5 cm
    stamp, estimate, published = 0.1, None, first
    for k in range(2, 40):
        stamp += 0.1
        estimate = Pose(np.eye(3), np.array([0.06 + 0.01 * (k - 1), 0.0, 0.0]))
        live._recent.append(_Recent(stamp, estimate, Pose.identity(), {}))
        odom = live._odom_pose(estimate, stamp)
        assert abs(odom.t[0] - published.t[0] - 0.01) <= 0.05 * 0.1 / LiveSmoother.ODOM_CONVERGENCE_S + 1e-9
        published = odom
    gap = 0.05 * (1.0 - 0.1 / LiveSmoother.ODOM_CONVERGENCE_S) ** 38          # a share of it each frame
    np.testing.assert_allclose(published.t, estimate.t - [gap, 0.0, 0.0], atol=1e-9)
    assert gap < 1e-3


def test_a_rig_that_stops_stands_still_in_the_live_pose(loop, monkeypatch):
    """Stop 61. Once the smoother has answered, a frame's translation is its last velocity, dead reckoned; a rig that
    stopped kept that velocity in the live pose, for as long as the smoother lagged (a demo whose rig stood 2 s after
    the loop: /fixego/odom moved 28-40 cm over the 2 s). Once ``STAND_FRAMES`` frames in a row show no parallax the
    live pose stands, whether the smoother is close behind (the carried step) or far (the solved one). Here the
    smoother answers until the stop, then goes silent, as the live child seconds behind."""
    def run() -> tuple[np.ndarray, np.ndarray]:
        live = LiveSmoother(RIG, EstimatorConfig(solver=SolverConfig(sigma=1.0 / F)), inline=True)
        results, _ = _feed(live, loop, wait=False)
        assert live.smoothed_results > 0 and np.linalg.norm(results[-1].pose.t) > 0.5
        live._conn = _Silent()
        standing = [live.update(o) for o in loop.standing(len(loop.observations) - 1, 10)]      # 2 s
        return results[-1].pose.t, np.array([r.pose.t for r in standing])

    n = LiveSmoother.STAND_FRAMES
    at_stop, standing = run()
    assert 0.01 < np.linalg.norm(standing[n - 2] - at_stop) < 0.2         # on at the smoother's speed until then
    assert np.linalg.norm(standing[n - 1:] - standing[n - 2], axis=1).max() < 1e-9      # then it stands
    monkeypatch.setattr(LiveSmoother, '_standing', lambda self, pairs, rays: False)     # as before
    at_stop, standing = run()
    assert np.linalg.norm(standing[-1] - at_stop) > 0.2        # ran on at the speed it had (measured 0.39 m)


def test_one_frame_without_parallax_does_not_stop_the_live_pose():
    """The stand needs ``STAND_FRAMES`` frames in a row without parallax: a frame with parallax starts the count
    again."""
    from fixego_ros.estimation.coplanarity import RayPairs
    from fixego_ros.estimation.twoframe import TwoFrameSolver, kabsch_rotation

    live = LiveSmoother.__new__(LiveSmoother)          # the parent's bookkeeping only: no child process
    live.solver = TwoFrameSolver(SolverConfig(sigma=1.0 / F))
    live._still_frames = 0
    rays = np.random.default_rng(0).normal(size=(30, 3)) + [0.0, 0.0, 4.0]
    still = RayPairs.build([(rays, rays, np.zeros(3), 1.0)])
    moved = RayPairs.build([(rays, rays - [0.0, 0.0, 0.3], np.zeros(3), 1.0)])
    frames = [still, still, moved, still, still, still, still]
    standing = [live._standing(p, kabsch_rotation(p.a, p.b)) for p in frames]
    assert standing == [False, False, False, False, False, True, True]


def test_inline_reports_the_resections_its_smoother_rejected(loop, monkeypatch):
    """The count the node puts on /diagnostics (smoother_resections_rejected) is the smoother's: one frame on the arc
    whose resection turns 15 deg too far is placed at the two-frame step's rotation and counted."""
    config = EstimatorConfig(solver=SolverConfig(sigma=1.0 / F))
    clean = LiveSmoother(RIG, config, inline=True)
    _feed(clean, loop, wait=False)
    perturb_resection(monkeypatch, 38, 15.0)
    inline = LiveSmoother(RIG, config, inline=True)
    _feed(inline, loop, wait=False)
    assert inline.resections_rejected == inline._conn._server.smoother.resections_rejected
    assert inline.resections_rejected == clean.resections_rejected + 1


def _server(points=()) -> _Server:
    """The smoother's side as the gate sees it: the vergence stamps it has been told of (none matched to a frame yet)
    and its skip count."""
    server = _Server(RIG, EstimatorConfig())
    server._points = list(points)
    return server


def _frame(stamp: float, keyframe: bool):
    return Message.FRAME, FrameObservation(stamp, None, None, keyframe=keyframe)


def test_the_gate_takes_keyframes_measured_frames_and_one_frame_per_gap():
    """One rule for the child and for replay (stop 77): 30 Hz frames, a keyframe every 5th; between keyframes a frame
    once ``MIN_GAP_S`` has passed since the last one taken, and the frame of a measurement whatever the gap. The newest
    frame left out is held: a measurement that follows it, or a pause (``flush``), takes it in."""
    server = _server(points=[7 / 30])
    gate = _Gate(server)
    taken = []
    for k in range(12):
        for _, obs in gate.admit(*_frame(k / 30, keyframe=k % 5 == 0)):
            taken.append(round(obs.stamp * 30))
    assert taken == [0, 3, 5, 7, 10]                # 3: the gap; 7: its measurement; 5 and 10: keyframes
    assert server.skipped == 7 and gate.holding     # frame 11 held
    assert [round(o.stamp * 30) for _, o in gate.flush()] == [11]
    assert server.skipped == 6 and not gate.holding and gate.flush() == []
    point = (Message.POINT, (13 / 30, 'right', np.zeros(3), np.eye(3)))
    assert gate.admit(*_frame(13 / 30, keyframe=False)) == []          # 2 frames after 11: left out, held
    admitted = gate.admit(*point)                                       # its measurement follows: it goes in first
    assert [k for k, _ in admitted] == [Message.FRAME, Message.POINT]
    assert admitted[0][1].stamp == 13 / 30


def test_a_busy_child_also_leaves_out_a_frame_when_a_later_one_waits():
    gate = _Gate(_server())
    waiting = [_frame(1.0, keyframe=False)]
    assert gate.admit(*_frame(0.0, keyframe=False), queue=waiting) == []
    assert gate.admit(*_frame(0.5, keyframe=True), queue=waiting) != []      # a keyframe always goes in
    assert gate.admit(*waiting[0]) != []


@pytest.mark.parametrize('inline', [True, False], ids=['inline', 'child'])
def test_the_last_frame_goes_into_the_graph_when_the_frames_stop(loop, inline):
    """A run's last frame, left out by the gap (here 10 ms after the one before), still goes into the graph: inline
    when the caller drains after its last frame, in the child once no frame has come for ``FLUSH_S``. Until stop 77
    replay never smoothed such a frame, and its terminal pose was the fast one."""
    backend = LiveSmoother(RIG, EstimatorConfig(solver=SolverConfig(sigma=1.0 / F)), inline=inline)
    try:
        observations = list(loop.observations[:12])
        last = observations[-1]
        observations.append(dataclasses.replace(last, stamp=last.stamp + 0.01, prev_stamp=last.stamp, keyframe=False))
        for obs in observations:
            backend.update(obs)
        revised = dict(backend.drain(WAIT_S))
        assert observations[-1].stamp in revised
        assert backend.behind_s == 0.0 and backend.frames_skipped == 0
        assert backend.smoothed_results == len(observations)
    finally:
        backend.close()
