"""Stereo synchroniser, observation row encoding, and the estimator's handling of gaps and disorder."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import numpy as np
import pytest

from fixego_ros.estimation.config import papers_config
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.frames import FrameObservation
from fixego_ros.estimation.status import StepStatus
from fixego_ros.experiments.point_scene import PRESETS, PointScene, random_motion_sequence
from fixego_ros.pipeline.messages import fixation_from_msg
from fixego_ros.pipeline.observation import (
    KIND_FLOW,
    KIND_TRACK,
    ROW_DTYPE,
    ObservationError,
    observation_to_rows,
    rows_to_observation,
)
from fixego_ros.pipeline.sync import StereoSync, SyncParams
from fixego_ros.tracking.fixation import NO_FIXATION_ID


def _feed(sync: StereoSync, side: str, t: float, now: float, joints=True, fix=True, fid=0) -> None:
    sync.add_image(side, t, f'{side}@{t}', now)
    if joints:
        sync.add_joints(side, t, 0.1 * t, -0.1 * t)
    if fix:
        sync.add_fixation(side, t, (320.0, 240.0), fid)


# ---------------------------------------------------------------------------------------------- sync
def test_sync_pairs_within_slop_and_keeps_order():
    sync = StereoSync(SyncParams(slop_s=0.005, max_wait_s=0.5))
    for k in range(5):
        _feed(sync, 'right', 1.0 + k / 30, now=k)
        _feed(sync, 'left', 1.0 + k / 30 + 0.002, now=k)
    frames = sync.pop_ready(now=4.0)
    assert [round(f.stamp, 6) for f in frames] == [round(1.0 + k / 30, 6) for k in range(5)]
    assert all(f.cameras['right'] and f.cameras['left'] for f in frames)
    f = frames[2]
    assert f.cameras['left'].image == f'left@{1.0 + 2 / 30 + 0.002}'
    assert f.cameras['right'].pan == pytest.approx(0.1 * f.stamp)
    assert sync.stats.stereo_frames == 5


def test_sync_waits_for_joints_then_interpolates():
    sync = StereoSync(SyncParams(max_wait_s=1.0))
    sync.add_image('right', 2.0, 'r', now=0.0)
    sync.add_image('left', 2.0, 'l', now=0.0)
    for s in ('right', 'left'):
        sync.add_fixation(s, 2.0, (1.0, 2.0), 7)
        sync.add_joints(s, 1.9, 0.0, 0.0)
    assert sync.pop_ready(now=0.1) == []              # the reading after the stamp has not come yet
    for s in ('right', 'left'):
        sync.add_joints(s, 2.1, 1.0, -1.0)
    (frame,) = sync.pop_ready(now=0.2)
    assert frame.cameras['right'].pan == pytest.approx(0.5)
    assert frame.cameras['left'].tilt == pytest.approx(-0.5)
    assert frame.cameras['right'].fixation_px == (1.0, 2.0) and frame.cameras['right'].fixation_id == 7


def test_sync_bounded_waits_give_single_camera_and_no_fixation_frames():
    sync = StereoSync(SyncParams(max_wait_s=0.2))
    _feed(sync, 'right', 1.0, now=0.0, fix=False)      # left never comes; no fixation for this frame
    assert sync.pop_ready(now=0.1) == []
    (frame,) = sync.pop_ready(now=0.3)
    assert frame.cameras['left'] is None
    assert frame.cameras['right'].fixation_px is None and frame.cameras['right'].fixation_id == -1
    assert sync.stats.single_camera_frames == 1 and sync.stats.no_fixation == 1
    assert sync.stats.partner_timeouts == 1 and sync.stats.partner_missing == 0    # waited, not known lost
    # no joints at all: the camera cannot be used, the frame is skipped after the wait
    sync.add_image('left', 2.0, 'l', now=1.0)
    assert sync.pop_ready(now=1.5) == []
    assert sync.stats.no_joints == 1


def test_sync_completes_at_once_on_an_explicit_no_fixation_and_still_waits_without_any_message():
    """camera_node's id -1 message completes the camera's part of the frame at once (no wait, no fixation); a
    stream without it (an older bag) still waits max_wait_s, then the camera enters without a fixation."""
    sync = StereoSync(SyncParams(max_wait_s=0.25))
    _feed(sync, 'right', 1.0, now=0.0, fid=4)
    _feed(sync, 'left', 1.0, now=0.0, fix=False)
    assert sync.add_fixation('left', 1.0, (0.0, 0.0), NO_FIXATION_ID)
    (frame,) = sync.pop_ready(now=0.0)                 # no time has passed: nothing waited
    r, left = frame.cameras['right'], frame.cameras['left']
    assert r.fixation_px == (320.0, 240.0) and r.fixation_id == 4
    assert left is not None and left.fixation_px is None and left.fixation_id == NO_FIXATION_ID
    assert left.pan == pytest.approx(0.1)
    assert sync.stats.stereo_frames == 1 and sync.stats.no_fixation == 1 and sync.stats.fixation_timeouts == 0
    # the same frame without the message: held back for max_wait_s
    _feed(sync, 'right', 2.0, now=1.0)
    _feed(sync, 'left', 2.0, now=1.0, fix=False)
    assert sync.pop_ready(now=1.2) == []
    (frame,) = sync.pop_ready(now=1.3)
    assert frame.cameras['left'].fixation_px is None and frame.cameras['left'].fixation_id == NO_FIXATION_ID
    assert sync.stats.no_fixation == 2 and sync.stats.fixation_timeouts == 1
    # an explicit none with a non-finite pixel is still none (the pixel is not used); a NaN stamp is rejected
    _feed(sync, 'right', 3.0, now=2.0, fix=False)
    _feed(sync, 'left', 3.0, now=2.0)
    assert sync.add_fixation('right', 3.0, (float('nan'), 0.0), NO_FIXATION_ID)
    assert not sync.add_fixation('right', float('nan'), None, NO_FIXATION_ID)
    (frame,) = sync.pop_ready(now=2.0)
    assert frame.cameras['right'].fixation_px is None and sync.stats.rejected == 1


def test_sync_does_not_wait_for_a_fixation_once_the_cameras_next_one_is_in():
    """A camera's fixation messages come in stamp order: one for a later stamp means its node never processed this
    image (a dropped sensor-data sample), so no fixation will come for it."""
    sync = StereoSync(SyncParams(max_wait_s=0.25))
    _feed(sync, 'right', 1.0, now=0.0)
    _feed(sync, 'left', 1.0, now=0.0, fix=False)                # left's node never saw this image
    assert sync.pop_ready(now=0.05) == []
    _feed(sync, 'right', 1.1, now=0.06)
    _feed(sync, 'left', 1.1, now=0.06)                          # its next fixation arrives
    frames = sync.pop_ready(now=0.06)
    assert [f.stamp for f in frames] == [1.0, 1.1]
    assert frames[0].cameras['left'].fixation_px is None and frames[1].cameras['left'].fixation_id == 0
    assert sync.stats.fixation_skipped == 1 and sync.stats.fixation_timeouts == 0 and sync.stats.no_fixation == 1


def test_fixation_message_parsing():
    def msg(x, y, z):
        return SimpleNamespace(point=SimpleNamespace(x=x, y=y, z=z))

    assert fixation_from_msg(msg(10.5, 20.25, 3.0)) == ((10.5, 20.25), 3)
    assert fixation_from_msg(msg(0.0, 0.0, -1.0)) == (None, NO_FIXATION_ID)
    for bad in (msg(1.0, 2.0, float('nan')), msg(float('nan'), 2.0, 0.0), msg(1.0, float('inf'), 5.0)):
        with pytest.raises(ValueError):
            fixation_from_msg(bad)


def test_sync_partner_past_means_no_wait_and_late_images_dropped():
    sync = StereoSync(SyncParams(max_wait_s=10.0))
    _feed(sync, 'right', 1.0, now=0.0)
    _feed(sync, 'right', 1.1, now=0.0)
    _feed(sync, 'left', 1.1, now=0.0)                  # left dropped its 1.0 frame
    frames = sync.pop_ready(now=0.0)
    assert [(f.stamp, f.cameras['left'] is not None) for f in frames] == [(1.0, False), (1.1, True)]
    assert sync.stats.partner_missing == 1 and sync.stats.partner_timeouts == 0   # lost on the way, no wait
    assert not sync.add_image('right', 1.05, 'late', now=0.0)
    assert not sync.add_image('right', float('nan'), 'nan', now=0.0)
    assert sync.stats.late_images == 1 and sync.stats.rejected == 1


def test_sync_flush_emits_everything_pending():
    sync = StereoSync(SyncParams(max_wait_s=100.0))
    _feed(sync, 'right', 1.0, now=0.0, fix=False)
    _feed(sync, 'left', 1.0, now=0.0, fix=False)
    assert sync.pop_ready(now=0.0) == []
    assert len(sync.pop_ready(now=0.0, flush=True)) == 1


# ---------------------------------------------------------------------------------------------- rows
@pytest.fixture(scope='module')
def scene_frames():
    cfg = PRESETS['dense']
    rng = np.random.default_rng(3)
    scene = PointScene(cfg, rng)
    steps = random_motion_sequence(cfg, 6, rng)
    poses, noisy, _ = scene.frames(steps)
    for k, obs in enumerate(noisy):
        obs.prev_stamp = float(k - 1) if k else None
    return scene.rig, poses, noisy


def test_rows_round_trip(scene_frames):
    _, _, obs = scene_frames
    o = copy.deepcopy(obs[2])
    o.right.joint_sigma = 0.004          # the camera node's 1-sigma of the readings, carried to the back end
    rows = observation_to_rows(o)
    assert rows.dtype == ROW_DTYPE
    assert np.sum(rows['kind'] == KIND_FLOW) == len(o.right.flow_prev) + len(o.left.flow_prev)
    back = rows_to_observation(o.stamp, rows)
    assert back.prev_stamp == o.prev_stamp
    for side in ('right', 'left'):
        a, b = o.camera(side), back.camera(side)
        np.testing.assert_allclose(b.fixation_ray, a.fixation_ray, atol=1e-12)
        np.testing.assert_allclose(b.cam_to_rig, a.cam_to_rig, atol=1e-12)
        np.testing.assert_allclose(b.flow_prev, a.flow_prev, atol=1e-12)
        np.testing.assert_allclose(b.flow_curr, a.flow_curr, atol=1e-12)
        assert b.fixation_id == a.fixation_id
    assert back.right.joint_sigma == 0.004 and back.left.joint_sigma == 0.0
    rows['sigma'][rows['kind'] == 0] = -1.0
    with pytest.raises(ObservationError, match='negative joint sigma'):
        rows_to_observation(o.stamp, rows)


def _with_tracks(o: FrameObservation, seed: int = 0) -> FrameObservation:
    """A copy of ``o`` with persistent tracks on both cameras: ids up to 2**53 - 1 (the largest a float64
    holds)."""
    o = copy.deepcopy(o)
    rng = np.random.default_rng(seed)
    for side, ids in (('right', np.array([0, 7, 123456789012, 2**53 - 1], np.int64)),
                      ('left', np.arange(40, 95, dtype=np.int64))):
        rays = rng.normal(size=(len(ids), 3)) + [0.0, 0.0, 3.0]
        o.camera(side).track_ids = ids
        o.camera(side).track_rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return o


def test_rows_round_trip_with_tracks(scene_frames):
    _, _, obs = scene_frames
    o = _with_tracks(obs[2])
    rows = observation_to_rows(o)
    assert np.sum(rows['kind'] == KIND_TRACK) == 4 + 55
    back = rows_to_observation(o.stamp, rows)
    for side in ('right', 'left'):
        a, b = o.camera(side), back.camera(side)
        assert b.track_ids.dtype == np.int64 and np.array_equal(b.track_ids, a.track_ids)   # exactly
        np.testing.assert_allclose(b.track_rays, a.track_rays, atol=1e-12)
        np.testing.assert_allclose(b.flow_prev, a.flow_prev, atol=1e-12)
    # no tracks: empty arrays of the right types
    plain = rows_to_observation(obs[3].stamp, observation_to_rows(obs[3]))
    assert plain.right.track_ids.dtype == np.int64 and plain.right.track_rays.shape == (0, 3)


def _track_rows(o: FrameObservation) -> tuple[np.ndarray, np.ndarray]:
    rows = observation_to_rows(o)
    return rows, np.flatnonzero(rows['kind'] == KIND_TRACK)


@pytest.mark.parametrize('corrupt, match', [
    (lambda r, t: r['x0'].__setitem__(t[1], 7.5), 'integers'),
    (lambda r, t: r['x0'].__setitem__(t[1], -1.0), 'integers'),
    (lambda r, t: r['x0'].__setitem__(t[1], 2.0**53), 'integers'),
    (lambda r, t: r['x0'].__setitem__(t[2], r['x0'][t[1]]), 'repeated'),
    (lambda r, t: r['y0'].__setitem__(t[1], 0.5), 'y0 = z0 = 0'),
    (lambda r, t: r['z1'].__setitem__(t[1], 3.0), 'unit'),
])
def test_rows_malformed_tracks_rejected(scene_frames, corrupt, match):
    _, _, obs = scene_frames
    rows, t = _track_rows(_with_tracks(obs[2], 1))
    corrupt(rows, t)
    with pytest.raises(ObservationError, match=match):
        rows_to_observation(obs[2].stamp, rows)


def test_rows_track_rows_need_their_camera_row(scene_frames):
    _, _, obs = scene_frames
    rows, _ = _track_rows(_with_tracks(obs[2], 2))
    keep = ~((rows['side'] == 1) & (rows['kind'] != KIND_TRACK))
    with pytest.raises(ObservationError, match='without a camera row'):
        rows_to_observation(obs[2].stamp, rows[keep])
    bad_ids = _with_tracks(obs[2], 3)
    bad_ids.right.track_ids = np.array([-3, 1, 2, 4], np.int64)
    with pytest.raises(ObservationError, match='track ids'):
        observation_to_rows(bad_ids)


def test_flow_node_yaml_lists_every_parameter_with_its_default():
    """config/flow_node.yaml repeats each declared parameter's default, with a comment."""
    from pathlib import Path

    from fixego_ros.nodes.flow_node import PARAMS
    from fixego_ros.pipeline.params import load_params_file

    path = Path(__file__).resolve().parents[1] / 'config' / 'flow_node.yaml'
    values = load_params_file(path, 'flow_node')
    assert values == {k: spec.default for k, spec in PARAMS.items()}
    for name in PARAMS:
        line = next(x for x in path.read_text().splitlines() if x.strip().startswith(f'{name}:'))
        assert '  # ' in line, f'{name}: no comment'


def test_rows_missing_camera_and_missing_fixation(scene_frames):
    _, _, obs = scene_frames
    o = obs[3]
    one = FrameObservation(o.stamp, o.right, None, o.prev_stamp)
    one.right.fixation_ray = None
    back = rows_to_observation(o.stamp, observation_to_rows(one))
    assert back.left is None and back.right.fixation_ray is None and back.right.fixation_id == -1
    assert len(back.right.flow_prev) == len(o.right.flow_prev)


@pytest.mark.parametrize('corrupt, match', [
    (lambda r: r['x1'].__setitem__(3, np.nan), 'NaN'),
    (lambda r: r['side'].__setitem__(0, 5), 'side'),
    (lambda r: r['kind'].__setitem__(2, 9), 'kind'),
    (lambda r: r['t0'].__setitem__(4, 123.0), 't0'),
    (lambda r: r['x0'].__setitem__(5, 2.0), 'unit'),
])
def test_rows_malformed_rejected(scene_frames, corrupt, match):
    _, _, obs = scene_frames
    rows = observation_to_rows(obs[2])
    corrupt(rows)
    with pytest.raises(ObservationError, match=match):
        rows_to_observation(obs[2].stamp, rows)


def test_rows_with_t0_after_stamp_rejected(scene_frames):
    _, _, obs = scene_frames
    rows = observation_to_rows(obs[2])
    with pytest.raises(ObservationError, match='not before'):
        rows_to_observation(float(rows['t0'][0]) - 0.5, rows)


# ---------------------------------------------------------------------------------------------- estimator
def test_estimator_bridges_a_gap_and_ignores_disorder(scene_frames):
    rig, _, obs = scene_frames
    est = Estimator(rig, papers_config(window=0))
    est.update(obs[0])
    r1 = est.update(obs[1])
    assert r1.status.usable
    res_old = est.update(obs[0])                        # out of order: ignored, nothing changes
    assert res_old.status is StepStatus.REJECTED and est.last_stamp == obs[1].stamp
    np.testing.assert_allclose(res_old.pose.t, r1.pose.t)
    # frame 2 lost: frame 3's flow starts at frame 2 -> one constant-velocity step bridges 1 -> 2
    res = est.update(obs[3])
    assert 'missing frames bridged' in res.message
    assert res.index == 2 and est.last_stamp == obs[3].stamp
    expected = r1.pose @ r1.step @ res.step
    np.testing.assert_allclose(res.pose.t, expected.t, atol=1e-9)
    # a flow that starts before the last frame cannot be placed: rejected
    bad = FrameObservation(obs[4].stamp, obs[4].right, obs[4].left, prev_stamp=obs[1].stamp)
    assert est.update(bad).status is StepStatus.REJECTED
    for o in obs[4:]:
        last = est.update(o)
    assert last.pose.is_finite() and np.all(np.isfinite(last.pose_covariance))
