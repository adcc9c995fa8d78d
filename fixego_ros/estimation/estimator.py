"""Incremental ego-motion estimator: two-frame solve per step, then local BA of the latest step.

Feed one :class:`FrameObservation` per synchronised frame; get a :class:`FrameResult` with the
refined pose (two-frame + local BA), the raw pose (two-frame only, the papers' comparison method), the
step covariance and a status. Memory is bounded by the BA window: only the last n frames' fixation
data and step motions are kept.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from fixego_ros.estimation.coplanarity import RayPairs
from fixego_ros.estimation.covariance import VAR_MAX
from fixego_ros.estimation.local_ba import MODES, BAProblem, BAResult, BATerm, refine_latest
from fixego_ros.estimation.status import StepStatus
from fixego_ros.estimation.twoframe import SolverConfig, TwoFrameResult, TwoFrameSolver
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.geometry.rotation import Pose, compose_all, rotation_angle


@dataclass
class CameraFrame:
    """One camera at one frame: its fixation ray and the flow pairs from the previous frame."""

    fixation_ray: np.ndarray | None   # rig-frame unit ray to the fixation point at this frame
    fixation_id: int                  # changes when the fixation point is re-selected
    cam_to_rig: np.ndarray            # optical frame -> rig frame at this frame (pan/tilt applied)
    flow_prev: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # rays at t-1, rig frame
    flow_curr: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # same points at t


@dataclass
class FrameObservation:
    stamp: float
    right: CameraFrame | None
    left: CameraFrame | None

    def camera(self, side: str) -> CameraFrame | None:
        return self.right if side == 'right' else self.left


Fixation = tuple[np.ndarray, int, np.ndarray]   # (rig-frame ray, fixation id, cam_to_rig)


def fixations_of(obs: FrameObservation) -> dict[str, Fixation | None]:
    """Each camera's valid fixation (finite ray) at this frame, or None."""
    out: dict[str, Fixation | None] = {}
    for side in SIDES:
        cam = obs.camera(side)
        ok = (cam is not None and cam.fixation_ray is not None
              and bool(np.all(np.isfinite(cam.fixation_ray))) and bool(np.all(np.isfinite(cam.cam_to_rig))))
        out[side] = (np.asarray(cam.fixation_ray, float), int(cam.fixation_id), cam.cam_to_rig) if ok else None
    return out


def step_pairs(rig: Rig, prev: dict[str, Fixation | None], obs: FrameObservation,
               fixation_weight: float = 1.0) -> RayPairs:
    """All ray pairs of one step: each camera's flow pairs, and its fixation pair when the fixation
    point was not re-selected between the two frames (same id)."""
    groups = []
    for side in SIDES:
        cam = obs.camera(side)
        if cam is None:
            continue
        c = rig.center(side)
        groups.append((cam.flow_prev, cam.flow_curr, c, 1.0))
        p = prev.get(side)
        if p is not None and cam.fixation_ray is not None and p[1] == cam.fixation_id:
            groups.append((p[0], cam.fixation_ray, c, fixation_weight))
    return RayPairs.build(groups)


@dataclass(frozen=True)
class EstimatorConfig:
    window: int = 3                  # n: frames in the local BA (3..10); 0 or 1 disables it
    mode: str = 'paper'              # 'paper' (BA cost alone, Powell) or 'joint'
    fixation_weight: float = 1.0     # weight of the fixation constraints relative to flow points
    max_step_translation: float = 1.0  # m; larger steps are rejected as jumps
    max_step_rotation: float = 0.35    # rad (~20 deg)
    reject_translation_std: float = VAR_MAX  # m; steps less certain than this are rejected
    solver: SolverConfig = field(default_factory=SolverConfig)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f'mode must be one of {MODES}, got {self.mode!r}')
        if self.window not in (0, 1) and not 3 <= self.window <= 10:
            raise ValueError(f'window must be 3..10 (or 0 to disable the local BA), got {self.window}')


@dataclass
class FrameResult:
    index: int
    stamp: float
    status: StepStatus
    pose: Pose                     # refined: rig at this frame in the rig frame at frame 0
    pose_raw: Pose                 # two-frame only
    step: Pose                     # refined step from the previous frame
    step_raw: Pose
    step_covariance: np.ndarray    # 6x6 over [rotation vector, T] of the step
    pose_covariance: np.ndarray    # 6x6 over [rotation vector, position] of ``pose`` (first order)
    message: str = ''
    twoframe: TwoFrameResult | None = None
    ba: BAResult | None = None


@dataclass
class _Slot:
    """What the window keeps of a frame."""

    fixation: dict[str, tuple[np.ndarray, int, np.ndarray] | None]
    step: Pose                      # refined step into this frame (identity for the first)


class Estimator:
    """Stateful incremental estimator (one instance per trajectory; :meth:`reset` restarts)."""

    def __init__(self, rig: Rig, config: EstimatorConfig | None = None) -> None:
        self.rig = rig
        self.config = config or EstimatorConfig()
        self.solver = TwoFrameSolver(self.config.solver)
        self.reset()

    def reset(self) -> None:
        n = max(self.config.window, 2)
        self._window: deque[_Slot] = deque(maxlen=n)
        self._index = -1
        self._pose = Pose.identity()
        self._pose_raw = Pose.identity()
        self._pose_cov = np.zeros((6, 6))
        self._last_step: Pose | None = None
        self._last_step_raw: Pose | None = None

    def _pairs(self, obs: FrameObservation) -> RayPairs:
        return step_pairs(self.rig, self._window[-1].fixation, obs, self.config.fixation_weight)

    def _ba_problem(self, obs: FrameObservation) -> tuple[BAProblem, bool]:
        """Terms for each camera over its window (never across a re-selection); and whether any
        camera has the full n-frame window (the papers wait for it before adjusting)."""
        n = self.config.window
        slots = list(self._window)
        terms: list[BATerm] = []
        full = False
        # prefixes[k] = P_{j,t-1} for j = index of slots[k]
        prefixes = [compose_all([s.step for s in slots[k + 1:]]) for k in range(len(slots))]
        for side in SIDES:
            cam = obs.camera(side)
            if cam is None or cam.fixation_ray is None:
                continue
            K = self.rig.camera(side)
            count = 0
            for k in range(len(slots) - 1, max(len(slots) - (n - 1), 0) - 1, -1):
                f = slots[k].fixation.get(side)
                if f is None or f[1] != cam.fixation_id:
                    break
                terms.append(BATerm(prefixes[k], f[0], cam.fixation_ray, self.rig.center(side),
                                    cam.cam_to_rig, K.fx, K.fy))
                count += 1
            full = full or count >= n - 1
        return BAProblem(terms), full

    def _accept(self, res: TwoFrameResult) -> tuple[bool, str]:
        cfg = self.config
        if not res.status.usable:
            return False, f'two-frame {res.status.value}: {res.message}'
        if not res.pose.is_finite():
            return False, 'non-finite solution'
        if np.linalg.norm(res.pose.t) > cfg.max_step_translation:
            return False, f'jump: |T| = {np.linalg.norm(res.pose.t):.3f} m > {cfg.max_step_translation}'
        if rotation_angle(res.pose.R) > cfg.max_step_rotation:
            return False, f'jump: rotation {np.degrees(rotation_angle(res.pose.R)):.1f} deg'
        if float(np.max(res.translation_std)) > cfg.reject_translation_std:
            return False, 'translation covariance too large'
        return True, ''

    def update(self, obs: FrameObservation) -> FrameResult:
        """Process one frame. Never raises on bad data; bad steps are flagged and predicted."""
        self._index += 1
        fix = fixations_of(obs)
        if self._index == 0 or not self._window:
            self._window.append(_Slot(fix, Pose.identity()))
            return FrameResult(self._index, obs.stamp, StepStatus.INIT, self._pose, self._pose_raw,
                               Pose.identity(), Pose.identity(), np.zeros((6, 6)), self._pose_cov.copy(),
                               'first frame')
        pairs = self._pairs(obs)
        tf = self.solver.solve(pairs, initial=self._last_step_raw)
        accepted, why = self._accept(tf)
        ba: BAResult | None = None
        if accepted:
            step_raw = tf.pose
            step = tf.pose
            cov = tf.covariance
            status = tf.status
            message = tf.message
            if self.config.window >= 3:
                problem, full = self._ba_problem(obs)
                if full and len(problem):
                    ba = refine_latest(problem, tf.pose, self.config.mode, pairs, self.config.solver.sigma)
                    refined = ba.pose
                    ok_ba = (np.linalg.norm(refined.t) <= self.config.max_step_translation
                             and rotation_angle(refined.R) <= self.config.max_step_rotation)
                    if ok_ba:
                        step = refined
                    else:
                        message += '; BA result rejected as a jump'
        else:
            step = self._last_step or Pose.identity()
            step_raw = self._last_step_raw or Pose.identity()
            cov = np.diag([1e-2] * 3 + [VAR_MAX] * 3) if self._last_step is None else \
                np.diag([1e-4] * 3 + [max(1e-2, float(np.sum(step.t**2)))] * 3)
            status = StepStatus.PREDICTED if self._last_step is not None else StepStatus(
                tf.status if not tf.status.usable else StepStatus.REJECTED)
            message = why + ('; constant-velocity prediction' if self._last_step is not None else '; held')
        self._pose_cov = self._propagate(self._pose, self._pose_cov, step, cov)
        self._pose = (self._pose @ step).normalized()
        self._pose_raw = (self._pose_raw @ step_raw).normalized()
        if accepted:
            self._last_step, self._last_step_raw = step, step_raw
        self._window.append(_Slot(fix, step))
        return FrameResult(self._index, obs.stamp, status, self._pose, self._pose_raw, step, step_raw,
                           cov, self._pose_cov.copy(), message, tf, ba)

    @staticmethod
    def _propagate(pose: Pose, pose_cov: np.ndarray, step: Pose, step_cov: np.ndarray) -> np.ndarray:
        """First-order covariance of ``pose @ step`` over [rotation (world), position (world)]."""
        R = pose.R
        J_prev = np.eye(6)
        # position p' = p + R t: d p' / d theta (world-frame rotation perturbation) = -[R t]x
        Rt = R @ step.t
        J_prev[3:, :3] = -np.array([[0.0, -Rt[2], Rt[1]], [Rt[2], 0.0, -Rt[0]], [-Rt[1], Rt[0], 0.0]])
        J_step = np.zeros((6, 6))
        J_step[:3, :3] = R
        J_step[3:, 3:] = R
        cov = J_prev @ pose_cov @ J_prev.T + J_step @ step_cov @ J_step.T
        cov = 0.5 * (cov + cov.T)
        return np.clip(cov, -VAR_MAX, VAR_MAX)
