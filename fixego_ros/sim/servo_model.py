"""ROS-free model of one camera's fixation servo, for writing bags without the VISCA loop.

It stands in for ``camera_node`` + a Sony EVI-D30 head: the camera chooses a well-textured scene point
near where it looks (the strongest corner near the image centre, as an operator would), then keeps it
at the image centre by commanding pan/tilt once per frame. The head follows the commands like the real
one: a first-order lag with speed limits and mechanical limits (pan ±100°, tilt ±25°, ~80°/s pan,
~50°/s tilt) and a serial latency; the controller leads its command by the target's estimated
velocity, as a tracking controller must to keep a moving point centred. The point is re-selected when
it would leave the head's range, is occluded, or comes too close. Joint readings are quantised like
VISCA position units (pan 8.8 units/deg, tilt 12 units/deg); the rendered image uses the true angles.

The head mechanics are their own small class (:class:`Head`), so the vergence step
(:mod:`fixego_ros.sim.vergence_step`) can read where the other head is between its commands, and the servo
exposes the primitives that step drives (``advance``, ``valid``, ``retarget``, ``command``, ``observe``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import cv2
import numpy as np

from fixego_ros.geometry.rig import Rig
from fixego_ros.geometry.rotation import Pose
from fixego_ros.sim.render import Renderer, camera_center_world, project_points
from fixego_ros.sim.world import World


@dataclass(frozen=True)
class ServoParams:
    """Head and controller constants (defaults: Sony EVI-D30 class head, 30 fps control loop)."""

    pan_limit_deg: float = 100.0
    tilt_limit_deg: float = 25.0
    pan_speed_deg_s: float = 80.0
    tilt_speed_deg_s: float = 50.0
    tau: float = 0.08  # s, first-order lag of the head
    latency: float = 0.02  # s, command transmission (15 bytes at 9600 baud ~ 16 ms)
    pan_units_per_deg: float = 8.8
    tilt_units_per_deg: float = 12.0
    quantize: bool = True
    reselect_margin_pan_deg: float = 10.0
    reselect_margin_tilt_deg: float = 5.0
    min_depth: float = 0.6
    min_separation: float = 1.0  # m from the other camera's fixation point (the papers: 2-3 m apart)
    max_depth: float = 6.0
    measurement_noise_px: float = 0.1
    select_window: float = 0.3  # fraction of the image (centred) searched for a new fixation point
    substep: float = 0.002  # s, integration step of the head dynamics


def required_readings(rig: Rig, side: str, rig_pose: Pose, point: np.ndarray) -> tuple[float, float]:
    """Joint readings (rad) that put world ``point`` on the optical axis of ``side`` (DESIGN.md §2)."""
    return rig.aim_readings(side, rig_pose.inverse().apply(np.asarray(point, dtype=float)))


def reading_sigmas(params: ServoParams) -> tuple[float, float]:
    """1-sigma (rad) of the pan and tilt readings: a quantised reading of a head at any angle is off by up to half a
    unit, uniformly (unit / sqrt 12); 0 unquantised. camera_node states the same for a moving head."""
    if not params.quantize:
        return 0.0, 0.0
    return (float(np.radians(1.0 / params.pan_units_per_deg)) / np.sqrt(12.0),
            float(np.radians(1.0 / params.tilt_units_per_deg)) / np.sqrt(12.0))


def quantized(params: ServoParams, pan: float, tilt: float) -> tuple[float, float]:
    """Joint readings (rad) as VISCA position units report true angles (pan, tilt)."""
    if not params.quantize:
        return pan, tilt
    pu, tu = params.pan_units_per_deg, params.tilt_units_per_deg
    return (np.radians(np.round(np.degrees(pan) * pu) / pu), np.radians(np.round(np.degrees(tilt) * tu) / tu))


@dataclass
class ServoState:
    """What one camera's servo looks like at one frame time."""

    t: float
    pan: float  # true mechanical angles (rad, device convention), used for rendering
    tilt: float
    pan_reading: float  # as a VISCA position query would report them (quantised)
    tilt_reading: float
    fixation_id: int
    point: np.ndarray  # world coordinates of the fixation point
    pixel: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))  # its true image position
    reselected: bool = False
    reading_sigmas: tuple[float, float] = (0.0, 0.0)   # 1-sigma (rad) of pan_reading, tilt_reading


class Head:
    """The pan/tilt mechanics: a first-order lag towards the last command, with speed limits; a command takes
    effect ``latency`` after it is sent."""

    def __init__(self, params: ServoParams) -> None:
        self.p = params
        self.pan = self.tilt = 0.0
        self.t = 0.0
        self.cmd = (0.0, 0.0)
        self.commands: list[tuple[float, float, float]] = []  # (effective time, pan, tilt)

    def place(self, t: float, pan: float, tilt: float) -> None:
        """Put the head at rest at (pan, tilt) at time ``t`` (the operator's initial aim)."""
        self.t, self.pan, self.tilt = t, pan, tilt
        self.cmd = (pan, tilt)

    def send(self, t: float, pan: float, tilt: float) -> None:
        """A position command sent at ``t`` (effective after the serial latency)."""
        self.commands.append((t + self.p.latency, pan, tilt))

    def advance(self, t: float) -> None:
        """Integrate the head from ``self.t`` to ``t`` under the queued commands."""
        p = self.p
        vmax = np.radians([p.pan_speed_deg_s, p.tilt_speed_deg_s])
        while self.t < t - 1e-12:
            while self.commands and self.commands[0][0] <= self.t + 1e-12:
                _, cp, ct = self.commands.pop(0)
                self.cmd = (cp, ct)
            dt = min(p.substep, t - self.t)
            if self.commands:
                dt = min(dt, max(self.commands[0][0] - self.t, 1e-9))
            err = np.array([self.cmd[0] - self.pan, self.cmd[1] - self.tilt])
            rate = np.clip(err / p.tau, -vmax, vmax)
            step = rate * dt
            step = np.where(np.abs(step) > np.abs(err), err, step)  # never overshoot the command
            self.pan += float(step[0])
            self.tilt += float(step[1])
            self.t += dt
        self.t = t

    def copy(self) -> Head:
        """An independent copy (its own command queue)."""
        out = copy.copy(self)
        out.commands = list(self.commands)
        return out

    def at(self, t: float) -> tuple[float, float]:
        """(pan, tilt) at a later time ``t`` if no other command is sent, without moving this head."""
        ahead = self.copy()
        ahead.advance(t)
        return ahead.pan, ahead.tilt


class FixationServo:
    """One camera's fixation servo; call :meth:`start` once, then :meth:`step` at increasing frame times."""

    def __init__(self, world: World, rig: Rig, side: str, renderer: Renderer, params: ServoParams = ServoParams(),
                 home_deg: tuple[float, float] | None = None, seed: int = 0) -> None:
        self.world, self.rig, self.side, self.renderer, self.p = world, rig, side, renderer, params
        # the papers' set-up: fixation points 2-3 m apart, so the cameras look slightly outwards
        if home_deg is None:
            home_deg = (22.5, 0.0) if side == 'right' else (-22.5, 0.0)
        self.home = (np.radians(home_deg[0]), np.radians(home_deg[1]))
        self.rng = np.random.default_rng([int(seed), 0 if side == 'right' else 1, 0x5E4])
        self.head = Head(params)
        self.fixation_id = -1
        self.point = np.full(3, np.nan)
        self._last_target: tuple[float, float, float] | None = None
        self._vel = np.zeros(2)
        self.reselections = 0
        self.partner: FixationServo | None = None  # the other camera: its point is not chosen again
        self.resume_point: np.ndarray | None = None  # own point to return to while verging on the partner's

    def own_point(self) -> np.ndarray:
        """The camera's own fixation point: the one it returns to while a vergence step has it elsewhere."""
        return self.resume_point if self.resume_point is not None else self.point

    @property
    def pan(self) -> float:
        return self.head.pan

    @property
    def tilt(self) -> float:
        return self.head.tilt

    # --- geometry helpers -------------------------------------------------------------------------
    def _limits_ok(self, pan: float, tilt: float) -> bool:
        return (abs(pan) <= np.radians(self.p.pan_limit_deg - self.p.reselect_margin_pan_deg)
                and abs(tilt) <= np.radians(self.p.tilt_limit_deg - self.p.reselect_margin_tilt_deg))

    def valid(self, rig_pose: Pose, point: np.ndarray) -> bool:
        """Whether this camera can fixate world ``point``: depth range, head range (with the re-selection
        margins) and an unoccluded view."""
        eye = camera_center_world(self.rig, self.side, rig_pose)
        depth = float(np.linalg.norm(point - eye))
        if not self.p.min_depth <= depth <= self.p.max_depth:
            return False
        if not self._limits_ok(*required_readings(self.rig, self.side, rig_pose, point)):
            return False
        return self.world.visible(eye, point)

    def quantized(self, pan: float, tilt: float) -> tuple[float, float]:
        """Readings as VISCA position units would report them."""
        return quantized(self.p, pan, tilt)

    # --- fixation point selection -----------------------------------------------------------------
    def select(self, rig_pose: Pose, pan: float, tilt: float) -> np.ndarray | None:
        """A well-textured, unoccluded surface point near the centre of the view at (pan, tilt), or None."""
        cam = self.rig.camera(self.side)
        img = self.renderer.render(self.side, rig_pose, pan, tilt, noise=False)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        w, h = cam.width, cam.height
        hw, hh = int(w * self.p.select_window / 2), int(h * self.p.select_window / 2)
        x0, y0 = int(cam.cx) - hw, int(cam.cy) - hh
        win = np.ascontiguousarray(img[y0:y0 + 2 * hh, x0:x0 + 2 * hw])
        corners = cv2.goodFeaturesToTrack(win, 40, 0.02, 5, blockSize=7)
        if corners is None:
            return None
        uv = corners.reshape(-1, 2) + np.array([x0, y0], float)
        # prefer strong corners close to the centre
        resp = cv2.cornerMinEigenVal(win, 7)
        score = np.array([resp[round(c[1] - y0), round(c[0] - x0)] for c in uv])
        score = score / (score.max() + 1e-12) - 0.5 * np.linalg.norm(uv - cam.center, axis=1) / max(hw, hh)
        eye = camera_center_world(self.rig, self.side, rig_pose)
        Rwc = rig_pose.R @ self.rig.cam_to_rig(self.side, pan, tilt)
        for i in np.argsort(-score):
            # a point whose neighbourhood is on the same surface (not on an occluding edge)
            offs = np.array([[0, 0], [12, 0], [-12, 0], [0, 12], [0, -12]], float)
            rays = cam.pixels_to_rays(uv[i] + offs) @ Rwc.T
            hits = [self.world.raycast(eye, r) for r in rays]
            if len({h[1] for h in hits}) != 1 or hits[0][1] < 0:
                continue
            point = eye + hits[0][0] * rays[0]
            other = self.partner.own_point() if self.partner is not None else None
            if other is not None and np.all(np.isfinite(other)) and \
                    np.linalg.norm(point - other) < self.p.min_separation:
                continue
            if self.valid(rig_pose, point):
                return point
        return None

    def reselect(self, rig_pose: Pose, first: bool = False) -> bool:
        """Choose a new point around the home direction (then nearby directions); False if none found."""
        hp, ht = self.home
        for dp, dt in ((0, 0), (15, 0), (-15, 0), (0, -10), (30, 0), (-30, 0), (45, -10), (-45, -10),
                       (60, 0), (-60, 0), (90, 0), (-90, 0)):
            pan, tilt = hp + np.radians(dp), ht + np.radians(dt)
            point = self.select(rig_pose, pan, tilt)
            if point is not None:
                self.retarget(point)
                if not first:
                    self.reselections += 1
                return True
        return False

    def retarget(self, point: np.ndarray) -> None:
        """Fixate world ``point`` from now on: a new fixation id (one id = one static point), and the
        controller forgets the old target's velocity."""
        self.point = np.asarray(point, dtype=float).copy()
        self.fixation_id += 1
        self._last_target = None
        self._vel[:] = 0.0

    # --- dynamics ---------------------------------------------------------------------------------
    def start(self, t: float, rig_pose: Pose) -> ServoState:
        """Pick the first fixation point and put the head exactly on it (the operator's initial aim)."""
        if not self.reselect(rig_pose, first=True):
            raise RuntimeError(f'{self.side}: no usable fixation point near the home direction')
        self.head.place(t, *required_readings(self.rig, self.side, rig_pose, self.point))
        return self._control(t, rig_pose, reselected=True)

    def advance(self, t: float) -> None:
        """Move the head on to time ``t`` under the commands sent so far."""
        self.head.advance(t)

    def step(self, t: float, rig_pose: Pose) -> ServoState:
        """Advance the head to frame time ``t``, report its state there, then send the next command."""
        self.advance(t)
        reselected = False
        if not self.valid(rig_pose, self.point):
            reselected = self.reselect(rig_pose, first=False)
        return self._control(t, rig_pose, reselected)

    def _control(self, t: float, rig_pose: Pose, reselected: bool) -> ServoState:
        self.command(t, rig_pose)
        return self.observe(t, rig_pose, reselected)

    def command(self, t: float, rig_pose: Pose) -> None:
        """One control period at ``t``: measure the fixation point's direction (with pixel noise) and send the
        head a command that leads it by its estimated velocity."""
        p = self.p
        target = np.array(required_readings(self.rig, self.side, rig_pose, self.point))
        cam = self.rig.camera(self.side)
        target += self.rng.normal(0.0, p.measurement_noise_px / cam.fx, 2)
        period = 0.0
        if self._last_target is not None and t > self._last_target[0]:
            period = t - self._last_target[0]
            v = (target - np.array(self._last_target[1:])) / period
            self._vel = v  # unsmoothed: smoothing lags and costs more than the noise it removes
        self._last_target = (t, float(target[0]), float(target[1]))
        # lead by the head's lag, the latency and half a control period (the command is held that long)
        cmd = target + self._vel * (p.tau + p.latency + 0.5 * period)
        lim = np.radians([p.pan_limit_deg, p.tilt_limit_deg])
        cmd = np.clip(cmd, -lim, lim)
        self.head.send(t, float(cmd[0]), float(cmd[1]))

    def observe(self, t: float, rig_pose: Pose, reselected: bool = False) -> ServoState:
        """The state at ``t`` (the head must have been advanced to ``t``): angles, readings, fixation pixel."""
        pr, tr = self.quantized(self.pan, self.tilt)
        pix, depth = project_points(self.rig, self.side, rig_pose, self.pan, self.tilt, self.point[None])
        pixel = pix[0] if depth[0] > 0 else np.full(2, np.nan)
        return ServoState(t, self.pan, self.tilt, pr, tr, self.fixation_id, self.point.copy(), pixel, reselected,
                          reading_sigmas(self.p))
