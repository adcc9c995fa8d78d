"""Stereo front end: synchronised camera samples -> the estimator's :class:`FrameObservation` (ROS-free).

Per camera and frame it turns the fixation pixel into a rig-frame ray and tracks flow from the previous
processed frame around the previous fixation pixel (:func:`~fixego_ros.tracking.flow.track_flow`).
Pixels become rig-frame rays with the pan/tilt of the frame they were seen in: the t-1 end of a flow
pair with the readings at t-1, the t end with those at t. That is what removes the cameras' own
rotation from the flow, so what remains is the rig's motion (DESIGN.md §2, §5).

Flow starts at a *keyframe*: by default the previous frame (the papers' scheme). At a high frame rate
consecutive frames are a few millimetres apart, far too little baseline for the two-frame solve, so a
:class:`KeyframePolicy` may keep one keyframe over several frames: each frame is then tracked from the
keyframe image directly (fixation keeps the image motion near the fixation point small, so LK still
follows), and the observation's ``prev_stamp`` names the keyframe. A new keyframe is taken after
``max_frames`` frames, once the rotation-compensated parallax reaches ``min_parallax_px``, when too few
of the keyframe's points still track, or when a fixation point is re-selected.

A camera contributes flow only if it also had a usable sample at the keyframe; a camera that is
missing, has an image of the wrong size or non-finite joint readings is left out of the observation
(None) for this frame, and the reason is kept in :attr:`StereoFrontEnd.last`.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from fixego_ros.estimation.estimator import CameraFrame, FrameObservation
from fixego_ros.estimation.twoframe import kabsch_rotation
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.tracking.flow import FlowCounts, FlowParams, FlowTracks, track_flow

# per-camera outcome of a frame
OK = 'ok'                        # flow tracked from the previous frame (it may still have 0 points)
NO_PREVIOUS = 'no_previous'      # first frame, or the camera was not usable at the previous frame
MISSING = 'missing'              # no sample for this camera
BAD_IMAGE = 'bad_image'          # not a 2-D image of the rig camera's size
BAD_JOINTS = 'bad_joints'        # non-finite pan/tilt readings


@dataclass
class CameraSample:
    """One camera at one synchronised frame."""

    gray: np.ndarray                          # uint8 HxW; kept by reference until the next frame: don't reuse it
    pan: float                                # joint readings (rad); the rig file's calibration maps them
    tilt: float
    fixation_px: tuple[float, float] | None   # None = no valid fixation this frame
    fixation_id: int = -1                     # -1 when none


@dataclass(frozen=True)
class KeyframePolicy:
    """When the front end takes a new keyframe (the frame later flow starts from)."""

    max_frames: int = 1                 # frames per keyframe at most; 1 = flow between consecutive frames
    min_parallax_px: float = 0.0        # new keyframe once the median rotation-compensated parallax reaches
                                        # this (0 = off)
    min_tracked_fraction: float = 0.5   # new keyframe when fewer of the keyframe's points still track

    def __post_init__(self) -> None:
        if self.max_frames < 1:
            raise ValueError(f'max_frames must be >= 1, got {self.max_frames}')
        if not (math.isfinite(self.min_parallax_px) and self.min_parallax_px >= 0):
            raise ValueError(f'min_parallax_px must be finite and >= 0, got {self.min_parallax_px}')
        if not 0.0 <= self.min_tracked_fraction <= 1.0:
            raise ValueError(f'min_tracked_fraction must be in [0, 1], got {self.min_tracked_fraction}')


def parallax_px(a: np.ndarray, b: np.ndarray, focal_px: float) -> float:
    """Median angle (in pixels at ``focal_px``) between rays ``a`` and the best-rotated ``b``: the flow
    left once the rig's rotation is removed, which is what carries the translation."""
    if len(a) < 3:
        return 0.0
    R = kabsch_rotation(a, b)
    cosang = np.clip(np.einsum('ij,ij->i', a, b @ R.T), -1.0, 1.0)
    return float(np.median(np.arccos(cosang)) * focal_px)


@dataclass(frozen=True)
class SideReport:
    """What happened to one camera in the last :meth:`StereoFrontEnd.process` call."""

    status: str = MISSING
    detail: str = ''                          # human-readable reason (also the flow's own reason)
    counts: FlowCounts = field(default_factory=FlowCounts)
    pairs: int = 0                            # flow pairs in the observation (after the finite-ray filter)
    has_fixation: bool = False
    window: tuple[int, int, int, int] | None = None


def _finite_px(px: tuple[float, float] | None) -> tuple[float, float] | None:
    if px is None:
        return None
    try:
        u, v = float(px[0]), float(px[1])
    except (TypeError, ValueError, IndexError):
        return None
    return (u, v) if math.isfinite(u) and math.isfinite(v) else None


class StereoFrontEnd:
    """Feed synchronised frames in order with :meth:`process`; :meth:`reset` forgets the previous frame.

    After each call, :attr:`last` holds a :class:`SideReport` per camera and :attr:`last_tracks` the
    pixel tracks behind the flow rays (None when no flow was tracked); :attr:`totals` sums the
    statuses and counts over all frames since construction.
    """

    def __init__(self, rig: Rig, params: FlowParams | None = None, keyframes: KeyframePolicy | None = None) -> None:
        self.rig = rig
        self.params = params or FlowParams()
        self.keyframes = keyframes or KeyframePolicy()
        self.totals: Counter[str] = Counter()
        self.reset()

    def reset(self) -> None:
        self._prev: dict[str, CameraSample | None] = dict.fromkeys(SIDES)   # the keyframe's samples
        self._prev_stamp: float | None = None                              # the keyframe's stamp
        self._since_key = 0
        self.last_parallax_px = 0.0
        self.last: dict[str, SideReport] = {side: SideReport() for side in SIDES}
        self.last_tracks: dict[str, FlowTracks | None] = dict.fromkeys(SIDES)

    @property
    def last_counts(self) -> dict[str, FlowCounts]:
        return {side: r.counts for side, r in self.last.items()}

    @property
    def stats(self) -> dict[str, int | str]:
        """The last frame per side as a flat dict (for a diagnostics message)."""
        out: dict[str, int | str] = {}
        for side, r in self.last.items():
            out[f'{side}.status'] = r.status
            out[f'{side}.detail'] = r.detail
            out[f'{side}.pairs'] = r.pairs
            out.update({f'{side}.{k}': v for k, v in r.counts.as_dict().items()})
        return out

    def process(self, stamp: float, samples: dict[str, CameraSample | None]) -> FrameObservation:
        """One synchronised frame; ``samples`` maps 'right'/'left' to a sample or None (missing keys = None)."""
        current: dict[str, CameraSample | None] = {}
        cams = {side: self._camera(side, samples.get(side), current) for side in SIDES}
        obs = FrameObservation(float(stamp), cams['right'], cams['left'], self._prev_stamp)
        self._since_key += 1
        obs.keyframe = self._new_keyframe(obs, current)
        if obs.keyframe:
            self._prev, self._prev_stamp, self._since_key = current, float(stamp), 0
        for side, r in self.last.items():
            self.totals[f'{side}.{r.status}'] += 1
            for k, v in r.counts.as_dict().items():
                self.totals[f'{side}.{k}'] += v
        return obs

    def _new_keyframe(self, obs: FrameObservation, current: dict[str, CameraSample | None]) -> bool:
        """Whether the frame just processed becomes the keyframe (see :class:`KeyframePolicy`)."""
        pol = self.keyframes
        if self._prev_stamp is None or self._since_key >= pol.max_frames:
            return True
        a, b = [], []
        for side in SIDES:
            key, now, rep = self._prev[side], current.get(side), self.last[side]
            if (key is None) != (now is None):
                return True                  # a camera came back or went away: restart from what is there
            if key is None or now is None:
                continue
            if key.fixation_id != now.fixation_id:
                return True                  # re-selected: the fixation pair needs a common keyframe
            if rep.counts.detected and rep.pairs < pol.min_tracked_fraction * rep.counts.detected:
                return True
            cam = obs.camera(side)
            if cam is not None and len(cam.flow_prev):
                a.append(cam.flow_prev)
                b.append(cam.flow_curr)
        if pol.min_parallax_px > 0 and a:
            self.last_parallax_px = parallax_px(np.concatenate(a), np.concatenate(b), self.rig.camera('right').fx)
            return self.last_parallax_px >= pol.min_parallax_px
        return False

    # ------------------------------------------------------------------------------------------------
    def _skip(self, side: str, status: str, detail: str) -> None:
        self.last[side] = SideReport(status, detail)
        self.last_tracks[side] = None

    def _camera(self, side: str, s: CameraSample | None, current: dict[str, CameraSample | None]) -> CameraFrame | None:
        current[side] = None
        if s is None:
            self._skip(side, MISSING, 'no sample')
            return None
        cam = self.rig.camera(side)
        img = s.gray
        if not isinstance(img, np.ndarray) or img.ndim != 2 or img.shape != (cam.height, cam.width):
            shape = getattr(img, 'shape', None)
            self._skip(side, BAD_IMAGE, f'image shape {shape}, rig camera is {cam.height}x{cam.width} (HxW)')
            return None
        try:
            pan, tilt = float(s.pan), float(s.tilt)
        except (TypeError, ValueError):
            pan = tilt = math.nan
        C = self.rig.cam_to_rig(side, pan, tilt)
        if not np.all(np.isfinite(C)):
            self._skip(side, BAD_JOINTS, f'pan/tilt readings not finite: {s.pan!r}, {s.tilt!r}')
            return None

        fix_px = _finite_px(s.fixation_px)
        ray = None
        if fix_px is not None:
            r = self.rig.pixels_to_rig_rays(side, np.array([fix_px]), pan, tilt)[0]
            ray = r if np.all(np.isfinite(r)) else None
        frame = CameraFrame(ray, int(s.fixation_id) if ray is not None else -1, C)

        prev = self._prev[side]
        current[side] = CameraSample(img, pan, tilt, fix_px, int(s.fixation_id) if fix_px is not None else -1)
        if prev is None:
            self.last[side] = SideReport(NO_PREVIOUS, 'no usable sample at the previous frame',
                                         has_fixation=ray is not None)
            self.last_tracks[side] = None
            return frame
        tracks = track_flow(prev.gray, img, prev.fixation_px, self.params)
        self.last_tracks[side] = tracks
        if len(tracks):
            a = self.rig.pixels_to_rig_rays(side, tracks.prev_px, prev.pan, prev.tilt)
            b = self.rig.pixels_to_rig_rays(side, tracks.curr_px, pan, tilt)
            good = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
            frame.flow_prev, frame.flow_curr = a[good], b[good]
        self.last[side] = SideReport(OK, tracks.reason, tracks.counts, len(frame.flow_prev), ray is not None,
                                     tracks.window)
        return frame
