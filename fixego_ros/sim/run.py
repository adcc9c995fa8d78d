"""The ROS-free simulation loop behind ``fixego sim``: trajectory + servo model + renderer, frame by frame.

Also holds the settings record and the rig resizing shared by the bag writer and the live node.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from fixego_ros.geometry.rig import Rig, make_rig
from fixego_ros.geometry.rotation import RIG_TO_BASE, Pose, rig_pose_to_base_link
from fixego_ros.sim.render import Renderer
from fixego_ros.sim.servo_model import FixationServo, ServoParams, ServoState
from fixego_ros.sim.trajectories import DT, Trajectory, make_trajectory, relative_poses, steps_duration
from fixego_ros.sim.world import World, make_room

EPOCH = 1_700_000_000.0  # s: bag stamps start here, so output is deterministic


@dataclass(frozen=True)
class SimSettings:
    """Everything that determines a simulated sequence (written next to the bag as ``sim.yaml``)."""

    trajectory: str = 'paper'
    seed: int = 0
    fps: float = 30.0
    encoding: str = 'mono8'
    noise_sigma: float = 2.0
    speed: float | None = None
    duration: float | None = None
    steps: int | None = None
    texel: float = 0.002
    epoch: float = EPOCH

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def resize_rig(rig: Rig, width: int, height: int) -> Rig:
    """The same rig at another resolution (angle of view kept: intrinsics scaled with the image)."""
    def scale(cam):
        sx, sy = width / cam.width, height / cam.height
        return dataclasses.replace(cam, width=int(width), height=int(height), fx=cam.fx * sx, fy=cam.fy * sy,
                                   cx=(cam.cx + 0.5) * sx - 0.5, cy=(cam.cy + 0.5) * sy - 0.5)
    return dataclasses.replace(rig, right=scale(rig.right), left=scale(rig.left))


def rig_with_hfov(rig: Rig, hfov_deg: float) -> Rig:
    """Two identical pinhole cameras of the given horizontal angle of view, keeping resolution and baseline."""
    base = make_rig(rig.right.width, rig.right.height, hfov_deg, float(np.linalg.norm(rig.c_L)))
    return dataclasses.replace(rig, right=base.right, left=base.left)


def build_trajectory(s: SimSettings) -> Trajectory:
    traj = make_trajectory(s.trajectory, speed=s.speed, seed=s.seed, duration=s.duration)
    if s.steps is not None:
        traj = traj.truncated(steps_duration(traj, s.steps))
    return traj


@dataclass
class Frame:
    """One simulated frame: both cameras' images and servo states, and the true poses."""

    index: int
    t: float  # seconds since the start of the trajectory
    rig_pose: Pose  # rig -> world
    gt_base: Pose  # base_link in odom (odom = base_link at frame 0)
    states: dict[str, ServoState]
    images: dict[str, np.ndarray]


class Simulation:
    """Runs the fixation servo model of both cameras along a trajectory and renders every frame."""

    def __init__(self, rig: Rig, settings: SimSettings = SimSettings(), world: World | None = None,
                 servo_params: ServoParams | None = None) -> None:
        self.rig, self.s = rig, settings
        self.world = world if world is not None else make_room(settings.seed, settings.texel)
        self.trajectory = build_trajectory(settings)
        self.renderer = Renderer(self.world, rig, settings.encoding, settings.noise_sigma, settings.seed)
        # selection renders without noise; its own renderer so it does not consume the noise stream
        self._select_renderer = Renderer(self.world, rig, 'mono8', 0.0, settings.seed)
        self.servos = {side: FixationServo(self.world, rig, side, self._select_renderer,
                                           servo_params or ServoParams(),
                                           seed=settings.seed) for side in ('right', 'left')}
        self.servos['right'].partner = self.servos['left']
        self.servos['left'].partner = self.servos['right']
        self.stamps, self.poses = self.trajectory.sample(settings.fps)

    def __len__(self) -> int:
        return len(self.stamps)

    def ground_truth(self) -> list[Pose]:
        """``base_link`` in ``odom`` (= ``base_link`` at frame 0) at every frame."""
        return [rig_pose_to_base_link(p) for p in relative_poses(self.poses)]

    def base_velocities(self, h: float = DT) -> np.ndarray:
        """(n, 3) true linear velocity of ``base_link`` in ``base_link`` (REP-105 twist) at every frame, m/s:
        central differences of the true poses over ±``h`` (one-sided at the ends)."""
        out = np.zeros((len(self.stamps), 3))
        for k, (t, pose) in enumerate(zip(self.stamps, self.poses, strict=True)):
            t0, t1 = max(t - h, 0.0), min(t + h, self.trajectory.duration)
            if t1 > t0:
                v_world = (self.trajectory.pose_at(t1).t - self.trajectory.pose_at(t0).t) / (t1 - t0)
                out[k] = RIG_TO_BASE @ pose.R.T @ v_world
        return out

    def frames(self) -> Iterator[Frame]:
        gt = self.ground_truth()
        for k, (t, pose) in enumerate(zip(self.stamps, self.poses, strict=True)):
            states = {side: (servo.start(t, pose) if k == 0 else servo.step(t, pose))
                      for side, servo in self.servos.items()}
            images = {side: self.renderer.render(side, pose, st.pan, st.tilt) for side, st in states.items()}
            yield Frame(k, float(t), pose, gt[k], states, images)
