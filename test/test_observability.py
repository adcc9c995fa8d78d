"""When the rays fix a step's metric length (estimation/observability.py): the lever arm's direction."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from fixego_ros.estimation.coplanarity import RayPairs
from fixego_ros.estimation.observability import length_invariant, lever_arm, lever_arm_angle, rig_lever_arm_angle
from fixego_ros.geometry.rig import make_rig
from fixego_ros.geometry.rotation import Pose, rot_y
from fixego_ros.sim.trajectories import make_trajectory, paper

RIG = make_rig(320, 240, 21.0, 0.2)
C_L = RIG.center('left')


def _pairs(motion: Pose, seed: int = 0) -> RayPairs:
    """Exact rays of random static points seen by both cameras before and after the rig ``motion``."""
    rng = np.random.default_rng(seed)
    groups = []
    for c in (RIG.center('right'), C_L):
        X = c + rng.uniform([-2, -1, 2], [2, 1, 6], (40, 3))            # rig frame at t, in front
        X1 = (X - motion.t) @ motion.R                                   # the same points in the rig frame at t+1
        groups.append((X - c, X1 - c, c, 1.0))
    return RayPairs.build(groups)


def _arc_step(yaw: float, radius: float, heading_offset: float = 0.0) -> Pose:
    """A step along a left-turning arc (rig frame: x right, y down, z forward) turning by ``yaw``; the heading
    is along the path unless ``heading_offset`` (rad) turns the rig against it."""
    t = radius * np.array([-(1 - math.cos(yaw)), 0.0, math.sin(yaw)])    # chord in the arc's start frame
    R = rot_y(-yaw)                                                      # yaw left = about -y (y down)
    if heading_offset:
        Q = rot_y(-heading_offset)     # the rig is turned by the offset at both ends (e.g. carried sideways)
        return Pose(Q.T @ R @ Q, Q.T @ t)
    return Pose(R, t)


@pytest.mark.parametrize('yaw_deg, radius', [(4.7, 0.477), (20.0, 1.5), (2.0, 5.0)])
def test_on_an_arc_along_the_heading_the_rays_cannot_tell_the_length(yaw_deg, radius):
    step = _arc_step(math.radians(yaw_deg), radius)
    assert lever_arm_angle(step.R, step.t, C_L) < 1e-6
    pairs = _pairs(step)
    for k in (0.3, 2.0, 10.0):
        assert length_invariant(step.R, step.t, pairs, k)


def test_straight_steps_cannot_tell_the_length():
    step = Pose(np.eye(3), np.array([0.0, 0.0, 0.05]))
    assert np.allclose(lever_arm(step.R, C_L), 0.0) and lever_arm_angle(step.R, step.t, C_L) == 0.0
    assert length_invariant(step.R, step.t, _pairs(step), 3.0)


def test_turning_against_the_path_makes_the_length_observable():
    step = _arc_step(math.radians(4.7), 0.477, heading_offset=math.radians(15.0))
    assert math.degrees(lever_arm_angle(step.R, step.t, C_L)) == pytest.approx(15.0, abs=0.5)
    assert not length_invariant(step.R, step.t, _pairs(step), 2.0, atol=1e-6)


def _step_angles(poses: list[Pose]) -> np.ndarray:
    """Lever-arm angle (deg) of every frame-to-frame step of a sampled trajectory (rig poses)."""
    return np.degrees([rig_lever_arm_angle(RIG, a.inverse() @ b) for a, b in itertools.pairwise(poses)])


def test_the_papers_loop_is_degenerate_on_every_step_within_a_segment():
    """Stadium loop at the shipped bag's rate: only the steps that straddle a straight/arc joint carry scale."""
    angles = _step_angles(paper().sample(5.1)[1])
    assert np.sum(angles > 0.1) <= 8                 # 4 joints, at most two steps each
    assert np.median(angles) < 1e-3
    # a random walk turns against its path: most of its turning steps carry some scale
    angles = _step_angles(make_trajectory('random').sample(10.0)[1])
    assert np.mean(angles > 1.0) > 0.5
