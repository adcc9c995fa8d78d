"""The ROS-free simulation loop behind ``fixego sim``: trajectory + servo model + renderer, frame by frame,
with the rig's vergence step when the settings ask for it (:attr:`SimSettings.vergence`).

Also holds the settings record, its limits (``fixego sim`` refuses values outside them before doing anything;
:class:`SimSettings` raises ValueError for them) and the rig resizing shared by the bag writer and the live node.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from fixego_ros.geometry.rig import Rig, make_rig
from fixego_ros.geometry.rotation import RIG_TO_BASE, Pose, rig_pose_to_base_link
from fixego_ros.sim.render import ENCODINGS, NOISE_MAX, Renderer
from fixego_ros.sim.servo_model import FixationServo, ServoParams, ServoState
from fixego_ros.sim.trajectories import (
    DT,
    NAMES,
    PAPER_STEPS,
    REST_RANGE,
    Trajectory,
    make_trajectory,
    relative_poses,
    steps_duration,
)
from fixego_ros.sim.vergence_measure import VERGENCE_MODES, VergenceMeasurement, VergenceParams, VergenceSource
from fixego_ros.sim.vergence_on_point import OnPointVergence
from fixego_ros.sim.vergence_step import VergenceStep
from fixego_ros.sim.world import TEXEL_RANGE, World, make_room
from fixego_ros.threads import portable_opencv

EPOCH = 1_700_000_000.0  # s: bag stamps start here, so output is deterministic

# Limits of the settings (closed intervals). Outside them a run overflows, exhausts memory, never ends or
# writes NaN/inf into the bag; the image size and angle of view are where the servo still finds a fixation point.
FPS_RANGE = (0.1, 1000.0)        # frames per second
SPEED_RANGE = (0.01, 100.0)      # m/s (the paper loop at 0.01 m/s takes 500 s)
DURATION_MAX = 3600.0            # s; a duration is > 0
SEED_MAX = 2**32 - 1             # seeds are 0..SEED_MAX (as sim_rig_node's)
SIZE_RANGE = (24, 8192)          # px, image width and height
HFOV_RANGE = (1.0, 170.0)        # deg, horizontal angle of view
NOISE_RANGE = (0.0, NOISE_MAX)   # grey levels
STEPS_RANGE = (0, PAPER_STEPS)   # paper loop step marks
MAX_FRAMES = 1_000_000           # frames of one run (every pose is held in memory; 1000 fps x 3600 s would not fit)


@dataclass(frozen=True)
class SimSettings:
    """Everything that determines a simulated sequence (written next to the bag as ``sim.yaml``).

    ``vergence``: ``off``, ``physical`` (the left head verges on the right's point at the start and at each new
    right fixation; :mod:`~fixego_ros.sim.vergence_step`) or ``measurements`` (the same measurements, heads
    undisturbed; :mod:`~fixego_ros.sim.vergence_on_point`). ``off`` here, so that code and records that predate
    it mean what they meant; ``fixego sim`` turns it on by default.
    """

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
    vergence: str = 'off'
    rest_s: float = 0.0               # standing still before the trajectory
    rest_end_s: float = 0.0           # standing still after it

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise ValueError('SimSettings: ' + '; '.join(problems))

    def problems(self) -> list[str]:
        """Every field outside its limit (module constants), as ``field must be ..., got value``."""
        out = []

        def within(name: str, value, lo: float, hi: float, lo_open: bool = False) -> None:
            ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value) \
                and (value > lo if lo_open else value >= lo) and value <= hi
            if not ok:
                out.append(f'{name} must be a finite number in {"(" if lo_open else "["}{lo:g}, {hi:g}], got '
                           f'{value!r}')

        if self.trajectory not in NAMES:
            out.append(f'trajectory must be one of {", ".join(NAMES)}, got {self.trajectory!r}')
        if self.vergence not in VERGENCE_MODES:
            out.append(f'vergence must be one of {", ".join(VERGENCE_MODES)}, got {self.vergence!r}')
        if self.encoding not in ENCODINGS:
            out.append(f'encoding must be one of {", ".join(ENCODINGS)}, got {self.encoding!r}')
        if not (isinstance(self.seed, numbers.Integral) and 0 <= self.seed <= SEED_MAX):
            out.append(f'seed must be an integer in 0..{SEED_MAX}, got {self.seed!r}')
        within('fps', self.fps, *FPS_RANGE)
        within('noise_sigma', self.noise_sigma, *NOISE_RANGE)
        within('texel', self.texel, *TEXEL_RANGE)
        within('epoch', self.epoch, 0.0, 4e9)
        if self.speed is not None:
            within('speed', self.speed, *SPEED_RANGE)
        if self.duration is not None:
            within('duration', self.duration, 0.0, DURATION_MAX, lo_open=True)
        within('rest_s', self.rest_s, *REST_RANGE)
        within('rest_end_s', self.rest_end_s, *REST_RANGE)
        if self.steps is not None and not (isinstance(self.steps, numbers.Integral) and STEPS_RANGE[0] <= self.steps
                                           <= STEPS_RANGE[1]):
            out.append(f'steps must be an integer in {STEPS_RANGE[0]}..{STEPS_RANGE[1]}, got {self.steps!r}')
        return out

    def to_dict(self) -> dict:
        """The fields (``sim.yaml``, the bag's ``fixego_sim`` custom data); ``vergence`` only when it is not
        ``off`` and ``rest_s`` / ``rest_end_s`` only when not 0, so a bag without them keeps the record it had
        before the options."""
        out = dataclasses.asdict(self)
        if out['vergence'] == 'off':
            del out['vergence']
        for rest in ('rest_s', 'rest_end_s'):
            if not out[rest]:
                del out[rest]
        return out


def resize_rig(rig: Rig, width: int, height: int) -> Rig:
    """The same rig at another resolution (angle of view kept: intrinsics scaled with the image)."""
    for name, v in (('width', width), ('height', height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f'image {name} must be a positive integer, got {v!r}')

    def scale(cam):
        sx, sy = width / cam.width, height / cam.height
        return dataclasses.replace(cam, width=int(width), height=int(height), fx=cam.fx * sx, fy=cam.fy * sy,
                                   cx=(cam.cx + 0.5) * sx - 0.5, cy=(cam.cy + 0.5) * sy - 0.5)
    return dataclasses.replace(rig, right=scale(rig.right), left=scale(rig.left))


def rig_with_hfov(rig: Rig, hfov_deg: float) -> Rig:
    """Two identical pinhole cameras of the given horizontal angle of view, keeping resolution and baseline."""
    if not (math.isfinite(hfov_deg) and 0.0 < hfov_deg < 180.0):
        raise ValueError(f'horizontal angle of view must be a finite number in (0, 180) deg, got {hfov_deg!r}')
    base = make_rig(rig.right.width, rig.right.height, hfov_deg, float(np.linalg.norm(rig.c_L)))
    return dataclasses.replace(rig, right=base.right, left=base.left)


def build_trajectory(s: SimSettings) -> Trajectory:
    traj = make_trajectory(s.trajectory, speed=s.speed, seed=s.seed, duration=s.duration)
    if s.steps is not None:
        traj = traj.truncated(steps_duration(traj, s.steps))
    return traj.after_rest(s.rest_s).then_rest(s.rest_end_s)


@dataclass
class Frame:
    """One simulated frame: both cameras' images and servo states, and the true poses."""

    index: int
    t: float  # seconds since the start of the trajectory
    rig_pose: Pose  # rig -> world
    gt_base: Pose  # base_link in odom (odom = base_link at frame 0)
    states: dict[str, ServoState]
    images: dict[str, np.ndarray]
    vergence: VergenceMeasurement | None = None   # a vergence measurement referring to this frame's stamp


class Simulation:
    """Runs the fixation servo model of both cameras along a trajectory and renders every frame.

    With vergence on, a frame is handed out only once no measurement under way can still refer to it (a
    measurement's window ends a few control ticks after the frame it refers to), so each frame carries its
    measurement; :attr:`vergence` keeps the measurements, failures and (physical) step records."""

    def __init__(self, rig: Rig, settings: SimSettings = SimSettings(), world: World | None = None,
                 servo_params: ServoParams | None = None, vergence_params: VergenceParams | None = None) -> None:
        # OpenCV's baseline code paths: its SIMD warps and remaps round by CPU, so the images depended on the machine
        # (and on the process: bench.seeds wrote a worker's first seed with the fast paths, the others after a replay
        # had switched them off; seed 28 replays 1.87 / 3.70 cm from AVX2's images, 2.01 / 3.96 from these; stop 87)
        portable_opencv()
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
        modes: dict[str, type[VergenceStep] | type[OnPointVergence]] = {'physical': VergenceStep,
                                                                         'measurements': OnPointVergence}
        self.vergence: VergenceSource | None = None
        if settings.vergence in modes:
            self.vergence = modes[settings.vergence](rig, self.servos, self.trajectory.pose_at, self.stamps,
                                                     vergence_params or VergenceParams(), settings.seed)

    def __len__(self) -> int:
        return len(self.stamps)

    def ground_truth(self) -> list[Pose]:
        """``base_link`` in ``odom`` (= ``base_link`` at frame 0) at every frame, with the rig's mount."""
        return [rig_pose_to_base_link(p, self.rig.mount) for p in relative_poses(self.poses)]

    def base_velocities(self, times: np.ndarray | None = None, h: float = DT) -> np.ndarray:
        """(n, 3) true linear velocity of ``base_link`` in ``base_link`` (REP-105 twist), m/s, at every frame or at
        ``times`` (s since the start): central differences of the true poses over ±``h`` (one-sided at the ends),
        with the rig's mount."""
        stamps = self.stamps if times is None else np.asarray(times, float)
        poses = self.poses if times is None else [self.trajectory.pose_at(float(t)) for t in stamps]
        out = np.zeros((len(stamps), 3))
        mount = self.rig.mount
        inv = mount.inverse() if mount is not None else None

        def origin(t: float) -> np.ndarray:       # base_link origin in the world
            pose = self.trajectory.pose_at(t)
            return pose.t if inv is None else (pose @ inv).t
        for k, (t, pose) in enumerate(zip(stamps, poses, strict=True)):
            t0, t1 = max(t - h, 0.0), min(t + h, self.trajectory.duration)
            if t1 > t0:
                v_world = (origin(t1) - origin(t0)) / (t1 - t0)
                out[k] = (RIG_TO_BASE if mount is None else mount.R) @ pose.R.T @ v_world
        return out

    def frames(self) -> Iterator[Frame]:
        gt = self.ground_truth()
        verg = self.vergence
        held: list[Frame] = []
        n_measured = 0
        for k, (t, pose) in enumerate(zip(self.stamps, self.poses, strict=True)):
            right = self.servos['right']
            states = {'right': right.start(t, pose) if k == 0 else right.step(t, pose)}
            if verg is None:
                left = self.servos['left']
                states['left'] = left.start(t, pose) if k == 0 else left.step(t, pose)
            else:
                states['left'] = verg.frame(k, float(t), pose, states['right'])
            images = {side: self.renderer.render(side, pose, st.pan, st.tilt) for side, st in states.items()}
            held.append(Frame(k, float(t), pose, gt[k], states, images))
            keep = None
            if verg is not None:
                for m in verg.measurements[n_measured:]:
                    held[m.frame - held[0].index].vergence = m
                n_measured, keep = len(verg.measurements), verg.pending_frame
            while held and (keep is None or held[0].index < keep):
                yield held.pop(0)
        if verg is not None:
            verg.finish()
        yield from held
