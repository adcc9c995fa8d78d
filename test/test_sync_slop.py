"""The synchroniser's automatic pairing tolerance (slop_s = 0): half the median frame period from the stamps."""

from __future__ import annotations

import pytest

from fixego_ros.pipeline.params import FLOW_PARAMS, params_getter, sync_params
from fixego_ros.pipeline.sync import AUTO_SLOP_MAX_S, AUTO_SLOP_MIN_S, StereoSync, SyncParams


def run_live(sync: StereoSync, n: int, fps: float, offset_s: float, latency_s: float = 0.004) -> list:
    """Two free-running cameras, the left ``offset_s`` after the right, each message delivered ``latency_s``
    after its stamp and the synchroniser drained after every message, as flow_node does."""
    events = []
    for k in range(n):
        for side, t in (('right', 1.0 + k / fps), ('left', 1.0 + k / fps + offset_s)):
            events.append((t + latency_s, side, t))
    frames = []
    for now, side, t in sorted(events):
        sync.add_image(side, t, f'{side}@{t:.4f}', now)
        frames += sync.pop_ready(now)
        sync.add_joints(side, t, 0.0, 0.0)
        frames += sync.pop_ready(now)
        sync.add_fixation(side, t, (320.0, 240.0), 1)
        frames += sync.pop_ready(now)
    return frames + sync.pop_ready(events[-1][0] + 1.0, flush=True)


@pytest.mark.parametrize('offset_s', [0.015, -0.015, 0.0, 0.008])
def test_auto_slop_pairs_every_frame_of_unsynchronised_30hz_cameras(offset_s):
    sync = StereoSync(sync_params(params_getter(FLOW_PARAMS)))     # the flow_node / replay default
    assert sync.params.slop_s == 0.0
    frames = run_live(sync, 60, 30.0, offset_s)
    assert len(frames) == 60 and sync.stats.stereo_frames == 60 and sync.stats.single_camera_frames == 0
    for k, f in enumerate(frames):          # each with its own partner, in order
        assert f.cameras['right'].image == f'right@{1.0 + k / 30:.4f}'
        assert f.cameras['left'].image == f'left@{1.0 + k / 30 + offset_s:.4f}'
    assert sync.frame_period_s == pytest.approx(1 / 30)
    assert sync.slop_s == pytest.approx(1 / 60)


def test_the_old_fixed_slop_splits_those_frames_and_an_explicit_value_wins():
    sync = StereoSync(SyncParams(slop_s=0.01))
    frames = run_live(sync, 30, 30.0, 0.015)
    assert sync.slop_s == 0.01 and sync.stats.stereo_frames == 0 and len(frames) == 60


def test_auto_slop_is_bounded_and_robust_to_dropped_frames():
    sync = StereoSync(SyncParams())
    assert sync.frame_period_s is None and sync.slop_s == AUTO_SLOP_MAX_S     # nothing measured yet
    for k in range(10):
        sync.add_image('right', k / 5.0, None, k / 5.0)                      # 5 Hz: half the period is 0.1 s
    assert sync.slop_s == AUTO_SLOP_MAX_S
    fast = StereoSync(SyncParams())
    for k in range(10):
        fast.add_image('left', k / 1000.0, None, 0.0)                       # 1 kHz
    assert fast.slop_s == AUTO_SLOP_MIN_S
    sync = StereoSync(SyncParams())
    stamps = [k / 30 for k in range(40) if k % 4 != 3]                       # every 4th frame dropped
    for t in stamps:
        sync.add_image('right', t, None, t)
    assert sync.slop_s == pytest.approx(1 / 60)                               # the median ignores the gaps


def test_the_readings_sigma_given_at_an_image_stamp_reaches_that_frame_only():
    """camera_node publishes a 1-sigma per image stamp (JointState effort); a frame at that stamp carries it, a frame
    whose angles are interpolated from readings at other stamps carries none (0: not given)."""
    from types import SimpleNamespace

    from fixego_ros.pipeline.messages import joint_sigma

    sync = StereoSync(SyncParams(slop_s=0.005))
    for side in ('right', 'left'):
        sync.add_joints(side, 1.0, 0.1, 0.0, 0.002)
        sync.add_joints(side, 1.1, 0.2, 0.0, 0.003)
    for t in (1.0, 1.05):
        for side in ('right', 'left'):
            sync.add_image(side, t, f'{side}@{t}', t)
            sync.add_fixation(side, t, (320.0, 240.0), 1)
    frames = sync.pop_ready(2.0, flush=True)
    assert [f.cameras['right'].joint_sigma for f in frames] == [0.002, 0.0]
    msg = SimpleNamespace(name=['left_pan', 'left_tilt'], position=[0.1, 0.2], effort=[0.001, 0.004])
    assert joint_sigma(msg, 'left') == 0.004
    assert joint_sigma(SimpleNamespace(name=['left_pan', 'left_tilt'], position=[0.1, 0.2], effort=[]), 'left') == 0.0
    assert joint_sigma(SimpleNamespace(name=['left_pan', 'left_tilt'], position=[0.1, 0.2],
                                       effort=[float('nan'), 0.1]), 'left') == 0.0
