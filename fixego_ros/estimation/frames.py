"""What the back ends take and give: one synchronised frame's observations, and one frame's result."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol, TypeVar

import numpy as np

from fixego_ros.estimation.coplanarity import RayPairs
from fixego_ros.estimation.local_ba import BAResult
from fixego_ros.estimation.status import StepStatus
from fixego_ros.estimation.twoframe import TwoFrameResult
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.geometry.rotation import Pose


@dataclass
class CameraFrame:
    """One camera at one frame: its fixation ray and the flow pairs from the previous frame."""

    fixation_ray: np.ndarray | None   # rig-frame unit ray to the fixation point at this frame
    fixation_id: int                  # changes when the fixation point is re-selected
    cam_to_rig: np.ndarray            # optical frame -> rig frame at this frame (pan/tilt applied)
    flow_prev: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # rays at t-1, rig frame
    flow_curr: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # same points at t
    # persistent point tracks seen at this frame (landmarks of the sliding window): ids never reused
    # within a camera, and the rig-frame unit ray of each at this frame
    track_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    track_rays: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    # 1-sigma (rad) of the pan/tilt readings behind cam_to_rig (camera_node's, growing with the head's rate and the
    # prediction time); 0 = not given: the back end's own mount sigma alone
    joint_sigma: float = 0.0


@dataclass
class FrameObservation:
    """One synchronised frame. ``prev_stamp`` is the stamp of the frame the flow starts from (None when
    unknown, e.g. synthetic data: then the previous frame); the estimator uses it to place the frame and
    to notice frames it never received. ``keyframe`` says whether later flow will start from this frame."""

    stamp: float
    right: CameraFrame | None
    left: CameraFrame | None
    prev_stamp: float | None = None
    keyframe: bool | None = None     # the front end will track later flow from this frame (None: unknown)

    def camera(self, side: str) -> CameraFrame | None:
        return self.right if side == 'right' else self.left


class _HasStamp(Protocol):
    stamp: float


_Stamped = TypeVar('_Stamped', bound=_HasStamp)

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


Tracks = dict[str, tuple[np.ndarray, np.ndarray]]   # side -> (track ids, rig-frame rays) of one frame


def tracks_of(obs: FrameObservation) -> Tracks:
    """Each camera's persistent tracks at this frame (ids and finite rig-frame rays)."""
    out: Tracks = {}
    for side in SIDES:
        cam = obs.camera(side)
        if cam is None:
            continue
        ids = np.asarray(cam.track_ids, np.int64).reshape(-1)
        rays = np.asarray(cam.track_rays, float).reshape(-1, 3)
        if len(ids) == len(rays):
            ok = np.all(np.isfinite(rays), axis=1)
            out[side] = (ids[ok], rays[ok])
    return out


def with_track_flow(obs: FrameObservation, earlier: Tracks) -> FrameObservation:
    """``obs`` with each camera's flow pairs replaced by the tracks it shares with an ``earlier`` frame: a step from
    that frame when the front end's own flow starts from a frame the estimator does not have."""
    now = tracks_of(obs)
    cams = {}
    for side in SIDES:
        cam = obs.camera(side)
        if cam is None:
            cams[side] = None
            continue
        prev, curr = np.zeros((0, 3)), np.zeros((0, 3))
        if side in earlier and side in now:
            _, ia, ib = np.intersect1d(earlier[side][0], now[side][0], assume_unique=True, return_indices=True)
            prev, curr = earlier[side][1][ia], now[side][1][ib]
        cams[side] = replace(cam, flow_prev=prev, flow_curr=curr)
    return replace(obs, right=cams['right'], left=cams['left'])


STAMP_TOLERANCE_S = 1e-6   # two stamps this close name the same frame


def at_stamp(frames: Sequence[_Stamped], stamp: float | None) -> _Stamped | None:
    """The frame of ``frames`` (oldest first) at ``stamp`` (within ``STAMP_TOLERANCE_S``), searched from the newest;
    None when there is none or ``stamp`` is None."""
    if stamp is None:
        return None
    for f in reversed(frames):
        if abs(f.stamp - stamp) <= STAMP_TOLERANCE_S:
            return f
        if f.stamp < stamp:
            return None
    return None


def span_start(frames: Sequence[_Stamped], seconds: float) -> _Stamped | None:
    """The newest of ``frames`` (oldest first) at least ``seconds`` before the last one: the start of a span to
    measure a speed or a motion over; None when there is none."""
    if len(frames) < 2:
        return None
    last = frames[-1].stamp
    return next((f for f in reversed(frames[:-1]) if last - f.stamp >= seconds), None)


@dataclass(frozen=True)
class JointWeighting:
    """How much a camera's rays count, given how sure its pan/tilt reading is (``CameraFrame.joint_sigma``, the
    1-sigma the camera node states: small when the head stands or turns slowly, 0.2-0.8 deg when a fast turn's angle
    is predicted). The reading rotates every ray the camera gives, so its variance adds to each ray's own. Readings
    up to ``nominal`` count fully (every simulated bag's and a steady head's), so the weighting only acts on fast
    turns: there a predicted angle was off by up to 1.4-2.7 deg in recorded demo runs, and bent the two-frame steps
    and the resection (docs/results.md "Stop 82": 19 runs' estimator inputs replayed, within 5 / 5 cm 6 -> 10, the
    median terminal error 6.4 -> 5.0 cm, the median mean 1.4 -> 2.0 cm)."""

    ray_sigma: float = 0.0      # rad: one ray's noise (pixel noise / focal length)
    nominal: float = 0.0        # rad: readings at most this uncertain count fully; 0 = every camera counts fully

    def weight(self, joint_sigma: float) -> float:
        """In (0, 1]: the factor on the camera's residuals in units of their noise."""
        if self.nominal <= 0.0 or not joint_sigma > self.nominal:
            return 1.0
        return math.sqrt((self.ray_sigma ** 2 + self.nominal ** 2) / (self.ray_sigma ** 2 + joint_sigma ** 2))


def step_pairs(rig: Rig, prev: dict[str, Fixation | None], obs: FrameObservation,
               fixation_weight: float = 1.0, joints: JointWeighting = JointWeighting()) -> RayPairs:
    """All ray pairs of one step: each camera's flow pairs, and its fixation pair when the fixation
    point was not re-selected between the two frames (same id); a camera's pairs weighted by ``joints``."""
    groups = []
    for side in SIDES:
        cam = obs.camera(side)
        if cam is None:
            continue
        c = rig.center(side)
        w = joints.weight(cam.joint_sigma)
        groups.append((cam.flow_prev, cam.flow_curr, c, w))
        p = prev.get(side)
        if p is not None and cam.fixation_ray is not None and p[1] == cam.fixation_id:
            groups.append((p[0], cam.fixation_ray, c, fixation_weight * w))
    return RayPairs.build(groups)


@dataclass
class FrameResult:
    index: int
    stamp: float
    status: StepStatus
    pose: Pose                     # refined: rig at this frame in the rig frame at frame 0
    pose_raw: Pose                 # two-frame only
    step: Pose                     # refined motion from the reference keyframe (the previous frame unless
    step_raw: Pose                 # the front end keeps a keyframe over several frames)
    step_covariance: np.ndarray    # 6x6 over [rotation vector, T] of the step
    pose_covariance: np.ndarray    # 6x6 over [rotation vector, position] of ``pose`` (first order)
    message: str = ''
    twoframe: TwoFrameResult | None = None
    ba: BAResult | None = None
    ref_stamp: float | None = None  # stamp of the keyframe ``step`` starts from
    placed: bool = True             # False: the frame was ignored (out of order, unknown reference)
    scale_observed: bool = False    # False until enough rotation (or a scale aid) has fixed the metric scale
    scale_note: str = ''            # why / how (one line, for diagnostics)
    # the scale was just measured: every earlier pose's position should be multiplied by this to be metric
    # (the path so far was built at a nominal speed; a trajectory kept by the caller can be rewritten)
    prefix_scale: float = 1.0
    # a blind step (predicted: no flow, e.g. both cameras re-selected at once) into the reference keyframe was
    # re-estimated from the rates on both sides of it: (stamp, pose, pose_raw) of that keyframe, to replace the
    # pose reported for it then (a kept trajectory is corrected; later poses already build on it)
    corrected: tuple[float, Pose, Pose] | None = None
    # the smoother's newer estimates of earlier frames still in its lag: (stamp, pose) each, to replace the poses
    # reported for them then (the live pose stays continuous; the path takes these)
    revised: tuple[tuple[float, Pose], ...] = ()
    # the pose to publish as odometry (pose, odom, TF): continuous, as REP-105's odom frame asks (a revision of
    # earlier frames does not make it jump; it converges on ``pose``); None = ``pose``
    odom: Pose | None = None

    @classmethod
    def rejected(cls, index: int, stamp: float, pose: Pose, pose_raw: Pose, why: str,
                 pose_covariance: np.ndarray | None = None, scale_observed: bool = False,
                 scale_note: str = '') -> FrameResult:
        """A frame a back end could not place (out of order, ...): the last poses again, state unchanged."""
        cov = np.zeros((6, 6)) if pose_covariance is None else pose_covariance.copy()
        return cls(index, stamp, StepStatus.REJECTED, pose, pose_raw, Pose.identity(), Pose.identity(),
                   np.zeros((6, 6)), cov, why, placed=False, scale_observed=scale_observed, scale_note=scale_note)
