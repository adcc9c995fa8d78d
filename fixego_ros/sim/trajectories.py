"""Rig trajectories in the world frame of :mod:`fixego_ros.sim.world` (x east, y north, z up).

A trajectory is sampled once on a fine time grid (``DT``) and interpolated, so the bag writer (fixed
frame rate) and the live node (wall-clock time) see the same continuous motion. The rig's attitude is
``R_z(yaw) @ RIG_IN_WORLD @ R_x(pitch) @ R_z(roll)``: yaw 0 faces north, positive yaw turns left,
positive pitch looks up, roll is about the rig's forward axis.

``paper`` is the papers' real experiment: straight 1.0 m in 20 steps, a 180° arc in 45 steps,
straight 1.0 m in 20 steps, a 180° arc in 45 steps: a closed ~5 m stadium loop of 130 steps. The rig
moves continuously (constant speed with short start/stop ramps); the times at which it passes the
131 step marks are kept in ``marks`` for step-wise evaluation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from fixego_ros.geometry.rotation import Pose, rot_x, rot_z

DT = 0.002  # s, grid of the precomputed trajectory
# rig axes (x right, y down, z forward) in the world when facing north
RIG_IN_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
NAMES = ('paper', 'straight', 'circle', 'random', 'walk')
PAPER_STEPS = 130   # step marks 0..PAPER_STEPS of the paper loop
# the fine grid of a trajectory has at most this many samples (20000 s): a vanishing speed or a huge duration
# would otherwise allocate without bound
MAX_GRID_POINTS = 10_000_000
REST_RANGE = (0.0, 600.0)        # s standing still before or after a trajectory (simulator options)
TRIPOD_HEIGHT = 1.2
HEAD_HEIGHT = 1.6
# centre of the area every trajectory stays in (the room's boxes stand outside a 2 m radius of it)
AREA_CENTRE = np.array([-0.48, 0.5])


def attitude(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rig -> world rotation."""
    return rot_z(yaw) @ RIG_IN_WORLD @ rot_x(pitch) @ rot_z(roll)


@dataclass(frozen=True)
class Trajectory:
    """Rig poses on a fine grid; ``marks`` are the times of the papers' steps (paper loop only)."""

    name: str
    t: np.ndarray
    xyz: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray
    marks: np.ndarray | None = None

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def pose_at(self, t: float) -> Pose:
        """Rig -> world pose at time ``t`` (clamped to the trajectory's span)."""
        t = float(np.clip(t, 0.0, self.duration))
        x = float(t / DT)
        i = min(int(np.floor(x)), len(self.t) - 2)
        a = x - i

        def lerp(v: np.ndarray):
            return (1.0 - a) * v[i] + a * v[i + 1]

        return Pose(attitude(lerp(self.yaw), lerp(self.pitch), lerp(self.roll)), lerp(self.xyz))

    def frame_count(self, fps: float) -> int:
        """Number of frames :meth:`sample` gives at ``fps``."""
        return int(np.floor(self.duration * fps + 1e-9)) + 1

    def sample(self, fps: float) -> tuple[np.ndarray, list[Pose]]:
        """Frame times ``0, 1/fps, ...`` up to the end, and the rig pose at each."""
        n = self.frame_count(fps)
        stamps = np.arange(n) / float(fps)
        return stamps, [self.pose_at(s) for s in stamps]

    def truncated(self, duration: float) -> Trajectory:
        """The first ``duration`` seconds."""
        n = min(len(self.t), int(np.floor(duration / DT + 1e-9)) + 1)
        marks = None if self.marks is None else self.marks[self.marks <= self.t[n - 1] + 1e-9]
        return replace(self, t=self.t[:n], xyz=self.xyz[:n], yaw=self.yaw[:n], pitch=self.pitch[:n],
                       roll=self.roll[:n], marks=marks)

    def path_length(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.xyz, axis=0), axis=1)))

    def after_rest(self, seconds: float) -> Trajectory:
        """The rig standing at the first pose for ``seconds`` (rounded to the grid), then this trajectory: a user
        who waits before walking, or a robot that starts late (the live demo's rig waited ~7 s in some runs)."""
        return self._held(seconds, at_end=False)

    def then_rest(self, seconds: float) -> Trajectory:
        """This trajectory, then the rig standing at its last pose for ``seconds`` (rounded to the grid): a rig that
        stops, where its heads have often just taken new points (docs/results.md "Stop 61")."""
        return self._held(seconds, at_end=True)

    def _held(self, seconds: float, at_end: bool) -> Trajectory:
        n = round(seconds / DT)
        if n <= 0:
            return self

        def held(v: np.ndarray) -> np.ndarray:
            return np.concatenate([v, np.repeat(v[-1:], n, axis=0)] if at_end else [np.repeat(v[:1], n, axis=0), v])
        marks = self.marks if self.marks is None or at_end else self.marks + n * DT
        return replace(self, t=np.arange(len(self.t) + n) * DT, xyz=held(self.xyz), yaw=held(self.yaw),
                       pitch=held(self.pitch), roll=held(self.roll), marks=marks)


def _grid(duration: float) -> np.ndarray:
    if not (math.isfinite(duration) and 0.0 <= duration <= MAX_GRID_POINTS * DT):
        raise ValueError(f'trajectory duration must be finite and within [0, {MAX_GRID_POINTS * DT:g}] s, got '
                         f'{duration!r} (speed too low or duration too long)')
    n = int(np.ceil(duration / DT - 1e-9)) + 1
    return np.arange(n) * DT


def _arc_length_profile(length: float, speed: float, ramp: float) -> tuple[np.ndarray, np.ndarray]:
    """Times and arc length s(t) for constant ``speed`` with linear speed ramps of ``ramp`` s at each end."""
    ramp = min(ramp, length / speed)
    cruise = (length - speed * ramp) / speed
    duration = cruise + 2 * ramp
    t = _grid(duration)
    acc = speed / ramp if ramp > 0 else np.inf
    s = np.where(t < ramp, 0.5 * acc * t ** 2,
                 np.where(t < ramp + cruise, 0.5 * speed * ramp + speed * (t - ramp),
                          length - 0.5 * acc * np.clip(duration - t, 0, None) ** 2))
    return t, np.clip(s, 0.0, length)


def _stadium(s: np.ndarray, straight: float, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position (x, y) and yaw along the papers' stadium loop at arc length ``s`` (start (0, 0), north)."""
    arc = np.pi * radius
    seg = np.array([straight, arc, straight, arc])
    ends = np.cumsum(seg)
    x = np.zeros_like(s)
    y = np.zeros_like(s)
    yaw = np.zeros_like(s)
    for k, (start, end) in enumerate(zip(np.concatenate([[0.0], ends[:-1]]), ends, strict=True)):
        m = (s >= start) & (s <= end) if k == 3 else (s >= start) & (s < end)
        u = s[m] - start
        if k == 0:
            x[m], y[m], yaw[m] = 0.0, u, 0.0
        elif k == 2:
            x[m], y[m], yaw[m] = -2 * radius, straight - u, np.pi
        else:
            phi = u / radius  # angle turned so far, to the left (CCW) about the arc's centre
            cx, cy, yaw0 = (-radius, straight, 0.0) if k == 1 else (-radius, 0.0, np.pi)
            x[m] = cx + radius * np.cos(yaw0 + phi)
            y[m] = cy + radius * np.sin(yaw0 + phi)
            yaw[m] = yaw0 + phi
    return x, y, yaw


def paper(speed: float = 0.2, straight: float = 1.0, radius: float | None = None,
          steps: tuple[int, int, int, int] = (20, 45, 20, 45), ramp: float = 0.5) -> Trajectory:
    """The papers' closed stadium loop (default radius makes the loop 5.0 m long)."""
    if radius is None:
        radius = (5.0 - 2 * straight) / (2 * np.pi)
    arc = np.pi * radius
    length = 2 * straight + 2 * arc
    t, s = _arc_length_profile(length, speed, ramp)
    x, y, yaw = _stadium(s, straight, radius)
    xyz = np.column_stack([x, y, np.full_like(x, TRIPOD_HEIGHT)])
    # step marks: equal steps within each segment
    seg = [straight, arc, straight, arc]
    marks_s = [0.0]
    for n, L in zip(steps, seg, strict=True):
        marks_s += list(marks_s[-1] + L * np.arange(1, n + 1) / n)
    marks = np.interp(marks_s, s, t)
    zero = np.zeros_like(t)
    return Trajectory('paper', t, xyz, yaw, zero, zero.copy(), marks)


def straight_line(speed: float = 0.2, length: float = 2.0, ramp: float = 0.5) -> Trajectory:
    """Straight north from (0, -0.5) at tripod height."""
    t, s = _arc_length_profile(length, speed, ramp)
    xyz = np.column_stack([np.zeros_like(s), s - 0.5, np.full_like(s, TRIPOD_HEIGHT)])
    zero = np.zeros_like(t)
    return Trajectory('straight', t, xyz, zero, zero.copy(), zero.copy())


def circle(speed: float = 0.2, radius: float = 0.6, turns: float = 1.0, ramp: float = 0.5) -> Trajectory:
    """Full turn(s) to the left on a circle, facing along it, starting at (0, 0) facing north."""
    t, s = _arc_length_profile(2 * np.pi * radius * turns, speed, ramp)
    phi = s / radius
    xyz = np.column_stack([-radius + radius * np.cos(phi), radius * np.sin(phi), np.full_like(s, TRIPOD_HEIGHT)])
    zero = np.zeros_like(t)
    return Trajectory('circle', t, xyz, phi, zero, zero.copy())


def _smooth_noise(rng: np.random.Generator, t: np.ndarray, n: int = 6, fmin: float = 0.03,
                  fmax: float = 0.4) -> np.ndarray:
    """Sum of random sinusoids, unit RMS: smooth (no corners) and seeded."""
    f = np.exp(rng.uniform(np.log(fmin), np.log(fmax), n))
    ph = rng.uniform(0, 2 * np.pi, n)
    a = rng.uniform(0.5, 1.0, n)
    out = np.sum(a[:, None] * np.sin(2 * np.pi * f[:, None] * t[None, :] + ph[:, None]), axis=0)
    return out / np.sqrt(0.5 * np.sum(a ** 2))


def random_walk(seed: int = 0, duration: float = 20.0, speed: float = 0.2, max_yaw_rate: float = 0.5,
                radius: float = 1.2) -> Trajectory:
    """Smooth seeded wandering inside a disc of ``radius`` around the area centre, with small tilts."""
    rng = np.random.default_rng([int(seed), 0x7A1])
    t = _grid(duration)
    w_free = max_yaw_rate * np.tanh(_smooth_noise(rng, t))
    v = speed * (0.75 + 0.25 * _smooth_noise(rng, t)) * np.clip(t / 0.5, 0, 1) * np.clip((duration - t) / 0.5, 0, 1)
    pitch = np.radians(2.0) * _smooth_noise(rng, t, fmin=0.05, fmax=0.5)
    roll = np.radians(1.5) * _smooth_noise(rng, t, fmin=0.05, fmax=0.5)
    z = TRIPOD_HEIGHT + 0.03 * _smooth_noise(rng, t, fmin=0.05, fmax=0.3)
    p = AREA_CENTRE.astype(float).copy()
    yaw = 0.0
    xy = np.zeros((len(t), 2))
    yaws = np.zeros(len(t))
    for i in range(len(t)):
        xy[i], yaws[i] = p, yaw
        d = p - AREA_CENTRE
        r = np.linalg.norm(d)
        w = w_free[i]
        if r > 0.6 * radius:
            # steer back towards the centre, more firmly the further out: keeps clear of the boxes
            want = np.arctan2(d[0], -d[1])  # yaw facing the centre (yaw 0 = north, CCW positive)
            err = (want - yaw + np.pi) % (2 * np.pi) - np.pi
            gain = min(1.0, (r - 0.6 * radius) / (0.4 * radius))
            w = (1 - gain) * w + gain * np.clip(2.0 * err, -max_yaw_rate * 1.5, max_yaw_rate * 1.5)
        yaw += w * DT
        p = p + v[i] * DT * np.array([-np.sin(yaw), np.cos(yaw)])
    xyz = np.column_stack([xy, z])
    return Trajectory('random', t, xyz, yaws, pitch, roll)


def walk(speed: float = 1.0, radius: float = 1.5, laps: float = 1.0, step_hz: float = 1.8,
         bob: float = 0.025, sway: float = 0.03, seed: int = 0) -> Trajectory:
    """Wearable rig on a walking person: a loop at head height with head bob, sway, pitch/roll/yaw wobble."""
    rng = np.random.default_rng([int(seed), 0x3A1C])
    length = 2 * np.pi * radius * laps
    t, s = _arc_length_profile(length, speed, 0.8)
    phi = s / radius
    walking = np.clip(np.gradient(s, t) / speed, 0, 1)  # gait amplitude follows the walking speed
    ph = rng.uniform(0, 2 * np.pi, 4)
    gait = 2 * np.pi * step_hz * t
    cx, cy = AREA_CENTRE
    # start south of the centre facing east, walking CCW around it
    base_x = cx + radius * np.sin(phi)
    base_y = cy - radius * np.cos(phi)
    yaw = phi - np.pi / 2
    lateral = sway * walking * np.sin(0.5 * gait + ph[0])  # body sways once per stride (two steps)
    x = base_x + lateral * np.cos(yaw)  # rig right = (cos yaw, sin yaw) in the world
    y = base_y + lateral * np.sin(yaw)
    z = HEAD_HEIGHT + bob * walking * np.cos(gait + ph[1])
    pitch = np.radians(1.5) * walking * np.sin(gait + ph[2])
    roll = np.radians(2.0) * walking * np.sin(0.5 * gait + ph[3])
    yaw = yaw + np.radians(2.0) * walking * np.sin(0.5 * gait + ph[0] + 0.5)
    return Trajectory('walk', t, np.column_stack([x, y, z]), yaw, pitch, roll)


def make_trajectory(name: str, speed: float | None = None, seed: int = 0,
                    duration: float | None = None) -> Trajectory:
    """Trajectory by name (``NAMES``); ``speed`` in m/s overrides the default; ``duration`` truncates.
    ValueError for an unknown name or a speed or duration that is not a finite number > 0."""
    if speed is not None and not (math.isfinite(speed) and speed > 0):
        raise ValueError(f'trajectory speed must be a finite number > 0 m/s, got {speed!r}')
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise ValueError(f'trajectory duration must be a finite number > 0 s, got {duration!r}')
    kw = {} if speed is None else {'speed': float(speed)}
    if name == 'paper':
        traj = paper(**kw)
    elif name == 'straight':
        traj = straight_line(**kw)
    elif name == 'circle':
        traj = circle(**kw)
    elif name == 'random':
        traj = random_walk(seed=seed, duration=duration or 20.0, **kw)
    elif name == 'walk':
        traj = walk(seed=seed, **kw)
    else:
        raise ValueError(f'unknown trajectory {name!r}; choose one of {", ".join(NAMES)}')
    if duration is not None and duration < traj.duration:
        traj = traj.truncated(duration)
    return traj


def steps_duration(traj: Trajectory, steps: int) -> float:
    """Time at which the paper loop reaches step mark ``steps`` (0..130)."""
    if traj.marks is None:
        raise ValueError(f'trajectory {traj.name!r} has no step marks (only paper has)')
    steps = int(np.clip(steps, 0, len(traj.marks) - 1))
    return float(traj.marks[steps])


def relative_poses(poses: list[Pose]) -> list[Pose]:
    """Poses relative to the first (``P_0^-1 P_k``): the rig at frame 0 becomes the origin."""
    inv0 = poses[0].inverse()
    return [inv0 @ p for p in poses]
