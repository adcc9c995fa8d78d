"""Simulator trajectories: the papers' 130-step stadium loop, continuity, staying clear of the boxes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from fixego_ros.geometry.rotation import Pose, rig_pose_to_base_link, rotation_angle
from fixego_ros.sim.run import SimSettings, build_trajectory
from fixego_ros.sim.trajectories import NAMES, make_trajectory, paper, relative_poses, steps_duration
from fixego_ros.sim.world import RoomSpec


def test_paper_loop_is_130_steps_5m_and_closed():
    traj = paper()
    assert len(traj.marks) == 131  # 130 steps between 131 marks
    pos = np.array([traj.pose_at(t).t for t in traj.marks])
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    np.testing.assert_allclose(steps[:20], 0.05, atol=1e-4)  # 1.0 m straight in 20 steps
    np.testing.assert_allclose(steps[65:85], 0.05, atol=1e-4)
    arc_chord = 2 * traj_radius(traj) * np.sin(np.pi / 45 / 2)
    np.testing.assert_allclose(steps[20:65], arc_chord, atol=1e-4)  # 180 deg arc in 45 equal steps
    np.testing.assert_allclose(steps[85:], arc_chord, atol=1e-4)
    assert traj.path_length() == pytest.approx(5.0, abs=0.02)
    start, end = traj.pose_at(0.0), traj.pose_at(traj.duration)
    assert np.linalg.norm(end.t - start.t) < 1e-6
    assert rotation_angle(start.R.T @ end.R) < 1e-6
    # heading turned by 180 deg after the first arc
    mid = traj.pose_at(traj.marks[65])
    assert rotation_angle(start.R.T @ mid.R) == pytest.approx(np.pi, abs=1e-6)
    assert steps_duration(traj, 20) == pytest.approx(traj.marks[20])


def traj_radius(traj) -> float:
    xy = traj.xyz[:, :2]
    return float((xy[:, 0].max() - xy[:, 0].min()) / 2)


@pytest.mark.parametrize('name', NAMES)
def test_trajectories_are_continuous_and_clear_of_the_boxes(name):
    traj = make_trajectory(name, seed=1)
    stamps, poses = traj.sample(30.0)
    assert stamps[0] == 0.0 and stamps[-1] <= traj.duration + 1e-9 and traj.duration > 5.0
    pos = np.array([p.t for p in poses])
    dpos = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    drot = [rotation_angle(a.R.T @ b.R) for a, b in itertools.pairwise(poses)]
    assert dpos.max() < 1.6 / 30.0  # no jumps: below a brisk walking speed per frame
    assert max(drot) < np.radians(3.0)
    assert dpos.sum() > 1.0  # it moves
    # no teleporting on the fine grid either: each step within the frame-level bound
    fine = np.linalg.norm(np.diff(traj.xyz, axis=0), axis=1)
    assert fine.max() < 1.6 * 0.002 + 1e-9
    spec = RoomSpec()
    assert np.all(pos[:, 0] > spec.x_min + 0.5) and np.all(pos[:, 0] < spec.x_max - 0.5)
    assert np.all(pos[:, 1] > spec.y_min + 0.5) and np.all(pos[:, 1] < spec.y_max - 0.5)
    for b in spec.boxes:
        gap = np.maximum(np.abs(pos[:, 0] - b.x) - b.sx / 2, np.abs(pos[:, 1] - b.y) - b.sy / 2)
        assert gap.min() > 0.3, f'{name} passes within {gap.min():.2f} m of a box'
    # ground truth: odom = base_link at the first frame
    gt0 = rig_pose_to_base_link(relative_poses(poses)[0])
    assert np.allclose(gt0.matrix(), np.eye(4))


def test_random_is_seeded_and_walk_bobs():
    a, b, c = (make_trajectory('random', seed=s) for s in (5, 5, 6))
    assert np.array_equal(a.xyz, b.xyz) and not np.allclose(a.xyz, c.xyz)
    walk = make_trajectory('walk')
    mid = (walk.t > 2.0) & (walk.t < walk.duration - 2.0)
    z = walk.xyz[mid, 2]
    assert 0.03 < z.max() - z.min() < 0.08  # head bob of a few cm
    # pitch oscillates at the step frequency (~1.8 Hz): many sign changes per second
    pitch = walk.pitch[mid]
    crossings = np.sum(np.diff(np.sign(pitch)) != 0) / (walk.t[mid][-1] - walk.t[mid][0])
    assert 2.5 < crossings < 5.0
    speed = np.linalg.norm(np.diff(walk.xyz[mid, :2], axis=0), axis=1) / 0.002
    assert 0.8 < np.median(speed) < 1.3


def test_truncation_and_interpolation():
    traj = make_trajectory('circle', duration=3.0)
    assert traj.duration == pytest.approx(3.0)
    full = make_trajectory('circle')
    for t in (0.0, 1.234, 2.9999):
        p, q = traj.pose_at(t), full.pose_at(t)
        assert np.allclose(p.t, q.t) and np.allclose(p.R, q.R)
    assert isinstance(traj.pose_at(10.0), Pose)  # clamped, not an error


def test_a_rest_holds_the_first_pose_then_the_trajectory_follows_shifted():
    plain = build_trajectory(SimSettings(steps=20))
    rested = build_trajectory(SimSettings(steps=20, rest_s=2.5))
    assert rested.duration == pytest.approx(plain.duration + 2.5, abs=1e-9)
    np.testing.assert_allclose(rested.marks, plain.marks + 2.5, atol=1e-9)
    start = plain.pose_at(0.0)
    for t in (0.0, 1.3, 2.5):
        np.testing.assert_allclose(rested.pose_at(t).matrix(), start.matrix(), atol=1e-12)
    for t in (0.4, 3.7, plain.duration):
        np.testing.assert_allclose(rested.pose_at(t + 2.5).matrix(), plain.pose_at(t).matrix(), atol=1e-9)
    assert rested.path_length() == pytest.approx(plain.path_length(), abs=1e-9)
    assert 'rest_s' not in SimSettings().to_dict() and SimSettings(rest_s=2.5).to_dict()['rest_s'] == 2.5


def test_a_rest_at_the_end_holds_the_last_pose_after_the_trajectory():
    plain = build_trajectory(SimSettings(steps=20))
    both = build_trajectory(SimSettings(steps=20, rest_s=1.0, rest_end_s=2.5))
    assert both.duration == pytest.approx(plain.duration + 3.5, abs=1e-9)
    np.testing.assert_allclose(both.marks, plain.marks + 1.0, atol=1e-9)     # the marks stay the trajectory's
    for t in (0.4, 3.7, plain.duration):
        np.testing.assert_allclose(both.pose_at(t + 1.0).matrix(), plain.pose_at(t).matrix(), atol=1e-9)
    end = plain.pose_at(plain.duration)
    for t in (0.1, 1.3, 2.5, 9.0):
        np.testing.assert_allclose(both.pose_at(plain.duration + 1.0 + t).matrix(), end.matrix(), atol=1e-12)
    assert both.path_length() == pytest.approx(plain.path_length(), abs=1e-9)
    assert 'rest_end_s' not in SimSettings().to_dict() and SimSettings(rest_end_s=2.5).to_dict()['rest_end_s'] == 2.5
    with pytest.raises(ValueError, match='rest_end_s'):
        SimSettings(rest_end_s=-1.0)
