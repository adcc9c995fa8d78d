"""Stereo front end: synchronised camera samples -> the estimator's :class:`FrameObservation` (ROS-free).

**Persistent tracks.** Per camera the front end keeps a set of point tracks with integer ids (never reused
within a camera, increasing). Every frame they are tracked from the previous processed frame with pyramidal
Lucas-Kanade and the forward-backward and correlation checks (:func:`~fixego_ros.tracking.flow.track_points`);
a track dies when it fails a check, leaves the image (border) or its track region (below), or is an epipolar
outlier. When the flow region lacks at least :data:`REPLENISH_FRACTION` of a target number (one, at least),
new corners are detected there (at least ``min_distance_px`` from the live tracks) and get new ids; a camera
holds at most the target number of tracks (the LK cost is per point). A track leaving its region still gives
its flow pair at that frame, then ends. Regions follow the fixation pixel at t (image centre without one):
``paper``: the papers' ``paper_points`` in the central ``paper_region_px`` square, tracks die on leaving it;
``window``: up to ``max_corners`` in the ``window_px`` square, tracks die on leaving that square grown by a
quarter of its side each way; ``full``: ``max_corners`` over the whole image. Each :class:`CameraFrame`
carries every live track at t (``track_ids``, ``track_rays``).

**Registered against the birth patch.** Each track keeps the patch it was detected on. After LK, about once every
``register_period_s`` (every frame at the papers' rates), the patch is registered with an affine warp at LK's
position (:func:`~fixego_ros.tracking.flow.register`), and the registered position is the track's. LK from frame to
frame drifts off the point as the scene comes closer; the registration does not (0.20 -> 0.06 px median after 16
frames on the papers' loop). A track whose patch no longer registers (correlation below ``REGISTER_MIN_NCC`` after
the warp, or landing far from LK) ends: it is not on one static point, e.g. a corner formed by two surfaces at
different depths that slides as they part. Those few tracks tilted the papers' loop by 0.3-0.5 deg on its first
straight (docs/results.md "Stop 74"). Over steps longer than :data:`PREWARP_MIN_STEP_S` LK runs on the previous image
warped by the points' affine motion (stop 53); at 30 Hz that warp cost a quarter of the front end and, with the
registration, changed no accuracy (docs/results.md "Stop 88").

**Predicted LK.** Image motion between frames can be large (a head lags its fixation point or swings
back at a pan limit), so LK starts from a prediction: the pan/tilt of both frames are known, and the
rig rotation over the step is predicted at constant angular velocity from the previous step (Kabsch
rotation of the previous step's track rays, both cameras; the left camera uses the step the right one
has just measured when it has enough tracks; a camera that lost most points is retried with the
rotation the other one measured). A track's ray at t-1 is rotated into the rig at t, into the
camera at t's pan/tilt and projected. When most points fail from the prediction, LK is tried once from
zero motion and the better attempt is kept (``totals`` counts ``lk_predicted``/``lk_zero``/``lk_retry``).

**Flow and keyframes.** Pixels become rig-frame rays with the pan/tilt of the frame they were seen in,
which removes the cameras' own rotation from the flow, so what remains is the rig's motion (DESIGN.md
§2, §5). Flow starts at a *keyframe*: by default the previous frame (the papers' scheme). A
:class:`KeyframePolicy` may keep one keyframe over several frames (at a high frame rate consecutive
frames are a few millimetres apart, too little baseline for the two-frame solve). The flow pairs of a
camera are its tracks alive at both the keyframe and t: ``flow_prev`` = the ray stored when the keyframe
was taken, ``flow_curr`` = the ray at t; the observation's ``prev_stamp`` names the keyframe. A new
keyframe is taken after ``max_frames`` frames, when the rig rotation keyframe -> t (Kabsch on the pairs)
exceeds ``max_rotation_deg``, once the rotation-compensated parallax reaches ``min_parallax_px``, when
too few of the keyframe's tracks survive, or when a fixation point is re-selected.

**Epipolar outliers.** With at least 8 pairs, a camera's pairs keyframe -> t must fit one essential
model ``a . (T_c x R b) = 0`` (rig-frame rays; T_c the camera centre's motion). RANSAC
(``cv2.findEssentialMat``, rays rotated into the camera's optical frame at the keyframe as normalised
coordinates, bound ``ransac_px`` / focal) drops the outliers from the pairs and kills their tracks. It
is skipped when the median rotation-compensated parallax is below ``ransac_min_parallax_px`` (E is then
degenerate and any pair fits some E).

Counts per camera and frame (:class:`~fixego_ros.tracking.flow.FlowCounts`): ``detected`` = live tracks
of t-1 tracked into t = ``lost + min_eig + outside + fb + ncc + epipolar + unregistered + kept``; ``new`` = tracks
started at t.

A camera contributes flow only if it also had a usable sample at the keyframe; a camera that is
missing, has an image of the wrong size or non-finite joint readings is left out of the observation
(None) for this frame, its tracks end, and the reason is kept in :attr:`StereoFrontEnd.last`.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from fixego_ros.estimation.frames import CameraFrame, FrameObservation
from fixego_ros.estimation.twoframe import MIN_ROTATION_PAIRS, kabsch_rotation
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.geometry.rotation import exp_so3, log_so3, rotation_angle
from fixego_ros.tracking.flow import (
    BirthPatches,
    Box,
    FlowCounts,
    FlowParams,
    FlowTracks,
    PointFlow,
    aligned,
    birth_patches,
    detect_corners,
    register,
    square_box,
    track_points,
    valid_box,
)

# new tracks are detected once the region lacks this share of its target (at least one): a detection costs the
# same for one corner as for twenty, and a frame usually loses one or two tracks
REPLENISH_FRACTION = 0.05

# LK starts from the previous image warped by the points' affine motion (:func:`~fixego_ros.tracking.flow.aligned`)
# only over steps longer than this: the papers' 5.1 Hz and 10 Hz bags as before, a 30 Hz stream (also across one
# skipped frame) without. At 30 Hz the warp cost a quarter of the front end and changed no accuracy on twelve bags of
# the loop; at 5.1 Hz leaving it out lost one seed of 32 and took `bags/paper` from 1.51 to 4.10 cm terminal
# (docs/results.md "Stop 88")
PREWARP_MIN_STEP_S = 0.075

# per-camera outcome of a frame
OK = 'ok'                        # tracked from the previous frame; flow from the keyframe (it may still have 0 pairs)
NO_PREVIOUS = 'no_previous'      # first frame, or the camera was not usable at the keyframe
MISSING = 'missing'              # no sample for this camera
BAD_IMAGE = 'bad_image'          # not a 2-D image of the rig camera's size
BAD_JOINTS = 'bad_joints'        # non-finite pan/tilt readings

# which LK attempt a camera's tracks came from
LK_PREDICTED = 'predicted'       # from the predicted positions
LK_ZERO = 'zero'                 # the prediction failed for most points; zero motion did better
LK_STEREO = 'stereo'             # ... and the rotation the other camera measured over this step did better
LK_FIXATION = 'fixation'         # ... and shifting every point by the fixation point's own image motion did better


@dataclass
class CameraSample:
    """One camera at one synchronised frame."""

    gray: np.ndarray                          # uint8 HxW; kept by reference until the next frame: don't reuse it
    pan: float                                # joint readings (rad); the rig file's calibration maps them
    tilt: float
    fixation_px: tuple[float, float] | None   # None = no valid fixation this frame
    fixation_id: int = -1                     # -1 when none
    joint_sigma: float = 0.0                  # 1-sigma (rad) of pan/tilt when the source gives one (0: not given)


@dataclass(frozen=True)
class KeyframePolicy:
    """When the front end takes a new keyframe (the frame later flow starts from)."""

    max_frames: int = 10                # frames per keyframe at most; 1 = flow between consecutive frames
    min_parallax_px: float = 0.0        # new keyframe once the median rotation-compensated parallax reaches
                                        # this (0 = off)
    min_tracked_fraction: float = 0.5   # new keyframe when fewer of the keyframe's tracks survive
    max_rotation_deg: float = 8.0       # new keyframe once the rig rotation keyframe -> t exceeds this (0 = off)

    def __post_init__(self) -> None:
        if self.max_frames < 1:
            raise ValueError(f'max_frames must be >= 1, got {self.max_frames}')
        if not (math.isfinite(self.min_parallax_px) and self.min_parallax_px >= 0):
            raise ValueError(f'min_parallax_px must be finite and >= 0, got {self.min_parallax_px}')
        if not 0.0 <= self.min_tracked_fraction <= 1.0:
            raise ValueError(f'min_tracked_fraction must be in [0, 1], got {self.min_tracked_fraction}')
        if not (math.isfinite(self.max_rotation_deg) and self.max_rotation_deg >= 0):
            raise ValueError(f'max_rotation_deg must be finite and >= 0, got {self.max_rotation_deg}')


def parallax_px(a: np.ndarray, b: np.ndarray, focal_px: float) -> float:
    """Median angle (in pixels at ``focal_px``) between rays ``a`` and the best-rotated ``b``: the flow
    left once the rig's rotation is removed, which is what carries the translation."""
    if len(a) < 3:
        return 0.0
    R = kabsch_rotation(a, b)
    cosang = np.clip(np.einsum('ij,ij->i', a, b @ R.T), -1.0, 1.0)
    return float(np.median(np.arccos(cosang)) * focal_px)


RANSAC_INPUT_STEP = 1e-7   # normalised coordinates (~2e-4 px here): what OpenCV's RANSAC is given is rounded to this


def _on_grid(x: np.ndarray) -> np.ndarray:
    """``x`` rounded to :data:`RANSAC_INPUT_STEP`. The rays come out of BLAS products whose last bits differ between
    CPU kernels, and a pair whose residual sits at RANSAC's bound is an inlier under one kernel and an outlier under
    the other: its track dies on one machine only, and the trajectories part (recorded demo run 1: first difference
    at 7.7 s, 1.04 cm RMS between OpenBLAS Prescott and the default kernel; docs/results.md "Stop 48"). Rounded, both
    give OpenCV the same numbers (unless a value straddles a step: ~1e-9 per value)."""
    return np.round(x / RANSAC_INPUT_STEP) * RANSAC_INPUT_STEP


def epipolar_outliers(a: np.ndarray, b: np.ndarray, cam_to_rig: np.ndarray, focal_px: float,
                      threshold_px: float, min_parallax_px: float = 0.5) -> np.ndarray | None:
    """Outliers (N,) bool of one camera's ray pairs ``a`` (keyframe) -> ``b`` (now), both rig frame, under
    an essential model ``a . (T x R b) = 0``: RANSAC (``cv2.findEssentialMat``, prob 0.999) on the rays
    rotated into the camera's optical frame ``cam_to_rig`` (so z > 0) as normalised coordinates, bound
    ``threshold_px / focal_px``. None when it was not run: fewer than 8 usable pairs, or a median
    rotation-compensated parallax below ``min_parallax_px`` (E degenerate: every pair fits some E)."""
    if len(a) < 8 or parallax_px(a, b, focal_px) < min_parallax_px:
        return None
    ac, bc = a @ cam_to_rig, b @ cam_to_rig            # rows: C^T a
    front = (ac[:, 2] > 0.05) & (bc[:, 2] > 0.05)
    if front.sum() < 8:
        return None
    x1 = _on_grid(ac[front, :2] / ac[front, 2:])
    x2 = _on_grid(bc[front, :2] / bc[front, 2:])
    E, mask = cv2.findEssentialMat(x1, x2, focal=1.0, pp=(0.0, 0.0), method=cv2.RANSAC, prob=0.999,
                                   threshold=float(threshold_px) / float(focal_px))
    if E is None or mask is None:
        return None
    out = np.zeros(len(a), bool)
    out[np.flatnonzero(front)[mask.ravel() == 0]] = True
    return out


@dataclass(frozen=True)
class Tracks:
    """Live point tracks of one camera at one frame."""

    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))   # (N,) int64
    px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))         # (N, 2) pixels
    rays: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))       # (N, 3) rig-frame unit rays

    def __len__(self) -> int:
        return len(self.ids)

    def select(self, keep: np.ndarray) -> Tracks:
        return Tracks(self.ids[keep], self.px[keep], self.rays[keep])

    def plus(self, other: Tracks) -> Tracks:
        return Tracks(np.concatenate([self.ids, other.ids]), np.concatenate([self.px, other.px]),
                      np.concatenate([self.rays, other.rays]))


def _in_box(px: np.ndarray, box: Box) -> np.ndarray:
    x0, y0, x1, y1 = box
    return (px[:, 0] >= x0) & (px[:, 0] < x1) & (px[:, 1] >= y0) & (px[:, 1] < y1)


@dataclass(frozen=True)
class _Births:
    """One camera's live tracks' birth patches and each one's affine since (:func:`~fixego_ros.tracking.flow.register`),
    by track id (ascending, as the tracks are)."""

    ids: np.ndarray
    patches: BirthPatches
    linear: np.ndarray      # (N, 2, 2)
    stamps: np.ndarray      # (N,) when each was last registered (born)

    def rows(self, ids: np.ndarray) -> np.ndarray | None:
        """The rows of ``ids``; None when one is not here."""
        rows = np.minimum(np.searchsorted(self.ids, ids), max(len(self.ids) - 1, 0))
        return rows if len(self.ids) and np.array_equal(self.ids[rows], ids) else None


@dataclass(frozen=True)
class SideReport:
    """What happened to one camera in the last :meth:`StereoFrontEnd.process` call."""

    status: str = MISSING
    detail: str = ''                          # human-readable reason
    counts: FlowCounts = field(default_factory=FlowCounts)
    pairs: int = 0                            # flow pairs in the observation (tracks at the keyframe and now)
    has_fixation: bool = False
    window: tuple[int, int, int, int] | None = None   # detection region at t
    tracks: int = 0                           # live tracks at t (new ones included)
    lk: str = ''                              # LK_PREDICTED | LK_ZERO | LK_FIXATION | LK_STEREO | '' (none)
    lk_retry: bool = False                    # another LK attempt was made after the prediction failed
    ransac: bool = False                      # the epipolar RANSAC ran


def _finite_px(px: tuple[float, float] | None) -> tuple[float, float] | None:
    if px is None:
        return None
    try:
        u, v = float(px[0]), float(px[1])
    except (TypeError, ValueError, IndexError):
        return None
    return (u, v) if math.isfinite(u) and math.isfinite(v) else None


class StereoFrontEnd:
    """Feed synchronised frames in order with :meth:`process`; :meth:`reset` forgets the previous frames
    and ends every track (ids still never repeat).

    After each call, :attr:`last` holds a :class:`SideReport` per camera and :attr:`last_tracks` the
    pixels behind the flow pairs (keyframe -> t; None when the camera had no keyframe); :attr:`totals`
    sums the statuses, counts and LK modes over all frames since construction.
    """

    def __init__(self, rig: Rig, params: FlowParams | None = None, keyframes: KeyframePolicy | None = None) -> None:
        self.rig = rig
        self.params = params or FlowParams()
        self.keyframes = keyframes or KeyframePolicy()
        self.totals: Counter[str] = Counter()
        self._next_id = dict.fromkeys(SIDES, 0)
        self.reset()

    def reset(self) -> None:
        self._prev: dict[str, CameraSample | None] = dict.fromkeys(SIDES)   # the keyframe's samples
        self._prev_stamp: float | None = None                              # the keyframe's stamp
        self._key: dict[str, Tracks] = {side: Tracks() for side in SIDES}  # tracks at the keyframe
        self._last: dict[str, CameraSample | None] = dict.fromkeys(SIDES)   # the previous frame's samples
        self._tracks: dict[str, Tracks] = {side: Tracks() for side in SIDES}  # live tracks there
        self._births: dict[str, _Births | None] = dict.fromkeys(SIDES)       # ... and their birth patches
        self._last_stamp: float | None = None
        self._omega = np.zeros(3)           # rig angular velocity of the last step (rad/s, rig frame)
        self._since_key = 0
        self.last_parallax_px = 0.0
        self.last_rotation_deg = 0.0
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
            out[f'{side}.tracks'] = r.tracks
            out[f'{side}.lk'] = r.lk
            out.update({f'{side}.{k}': v for k, v in r.counts.as_dict().items()})
        return out

    def process(self, stamp: float, samples: dict[str, CameraSample | None]) -> FrameObservation:
        """One synchronised frame; ``samples`` maps 'right'/'left' to a sample or None (missing keys = None)."""
        stamp = float(stamp)
        dt = stamp - self._last_stamp if self._last_stamp is not None else 0.0
        R_pred = exp_so3(self._omega * dt) if 0.0 < dt < 1.0 else np.eye(3)
        current: dict[str, CameraSample | None] = {}
        frames = {side: self._check(side, samples.get(side), current) for side in SIDES}
        # follow each camera's tracks; the rotation one camera measures predicts the other's
        follows: dict[str, _Follow | None] = {}
        measured: dict[str, np.ndarray] = {}
        for side in SIDES:
            follows[side] = f = self._follow(side, current[side], R_pred, dt) if frames[side] is not None else None
            if f is not None and len(f.step[0]) >= MIN_ROTATION_PAIRS:
                measured[side] = R_pred = kabsch_rotation(*f.step)
        for side in SIDES:            # a camera that lost most points: once more with the other's rotation
            f, other = follows[side], [R for o, R in measured.items() if o != side]
            if f is not None and other and 2 * f.flow.counts.kept < len(self._tracks[side]):
                follows[side] = self._follow(side, current[side], other[0], dt, f)
        step = [f.step for f in follows.values() if f is not None and len(f.step[0]) >= MIN_ROTATION_PAIRS]
        if step and dt > 0.0:
            self._omega = log_so3(kabsch_rotation(np.concatenate([a for a, _ in step]),
                                                  np.concatenate([b for _, b in step]))) / dt
        elif all(c is None for c in current.values()):
            self._omega = np.zeros(3)
        self._last_stamp = stamp
        cams = {side: self._finish(side, frames[side], current[side], follows[side], stamp, dt)
                if frames[side] is not None else None for side in SIDES}
        obs = FrameObservation(stamp, cams['right'], cams['left'], self._prev_stamp)
        self._since_key += 1
        obs.keyframe = self._new_keyframe(obs, current)
        if obs.keyframe:
            self._prev, self._prev_stamp, self._since_key = current, stamp, 0
            self._key = {side: self._tracks[side] if current[side] is not None else Tracks() for side in SIDES}
        for side, r in self.last.items():
            self.totals[f'{side}.{r.status}'] += 1
            for k, v in r.counts.as_dict().items():
                self.totals[f'{side}.{k}'] += v
            if r.lk:
                self.totals[f'{side}.lk_{r.lk}'] += 1
            self.totals[f'{side}.lk_retry'] += int(r.lk_retry)
            self.totals[f'{side}.ransac'] += int(r.ransac)
        return obs

    def _new_keyframe(self, obs: FrameObservation, current: dict[str, CameraSample | None]) -> bool:
        """Whether the frame just processed becomes the keyframe (see :class:`KeyframePolicy`)."""
        pol = self.keyframes
        self.last_parallax_px = self.last_rotation_deg = 0.0
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
            n_key = len(self._key[side])
            if n_key and rep.pairs < pol.min_tracked_fraction * n_key:
                return True
            cam = obs.camera(side)
            if cam is not None and len(cam.flow_prev):
                a.append(cam.flow_prev)
                b.append(cam.flow_curr)
        if not a:
            return False
        A, B = np.concatenate(a), np.concatenate(b)
        if len(A) >= 3:
            self.last_rotation_deg = math.degrees(rotation_angle(kabsch_rotation(A, B)))
            if pol.max_rotation_deg > 0 and self.last_rotation_deg > pol.max_rotation_deg:
                return True
        if pol.min_parallax_px > 0:
            self.last_parallax_px = parallax_px(A, B, self.rig.camera('right').fx)
            return self.last_parallax_px >= pol.min_parallax_px
        return False

    # ------------------------------------------------------------------------------------------------
    def _skip(self, side: str, status: str, detail: str) -> None:
        self.last[side] = SideReport(status, detail)
        self.last_tracks[side] = None
        self._last[side] = None
        self._tracks[side] = Tracks()
        self._births[side] = None

    def _regions(self, centre: tuple[float, float], shape: tuple[int, int]) -> tuple[Box, Box, int]:
        """(detection region, track region, target count) around the window centre at t."""
        p = self.params
        valid = valid_box(shape, p.border_px)
        if p.preset == 'full':
            return valid, valid, p.max_corners
        cx, cy = centre
        window = square_box(cx, cy, p.window_px, valid)
        if p.preset == 'paper':
            region = square_box(cx, cy, p.paper_region_px, window)
            return region, region, p.paper_points
        return window, square_box(cx, cy, p.window_px + 2 * (p.window_px // 4), valid), p.max_corners

    def _predict(self, side: str, tracks: Tracks, pan: float, tilt: float, R_pred: np.ndarray) -> np.ndarray:
        """Predicted pixels (N, 2) at t of tracks seen at t-1 (NaN where a point would be behind the camera):
        ray at t-1 -> rig at t (``R_pred`` = rig axes at t in the rig at t-1) -> camera at t -> pixel."""
        d = (tracks.rays @ R_pred) @ self.rig.cam_to_rig(side, pan, tilt)   # rows: C_t^T R^T r
        out = np.full((len(d), 2), np.nan)
        front = d[:, 2] > 1e-3
        if front.any():
            out[front] = self.rig.camera(side).rays_to_pixels(d[front])
        return out

    def _follow(self, side: str, now: CameraSample, R_pred: np.ndarray, dt: float,
                before: _Follow | None = None) -> _Follow | None:
        """Track the live tracks of the previous frame into ``now``, LK from the predicted positions. First call
        (``before`` None): when most points fail, once more from zero motion and once more shifted by the fixation
        point's image motion (a servo that lags a turn that starts or ends moves the whole window by tens of pixels,
        which neither the rig's last rate nor zero motion predicts); the best attempt wins. Second call: from the
        other camera's measured rotation, kept only if better than ``before``."""
        tracks, last = self._tracks[side], self._last[side]
        if last is None or not len(tracks):
            return None
        p = self.params
        guess = self._predict(side, tracks, now.pan, now.tilt, R_pred)
        if dt > PREWARP_MIN_STEP_S:
            warped, start, landed = aligned(last.gray, now.gray, tracks.px, p, guess)
            flow = track_points(warped, now.gray, start, p, landed)
        else:
            flow = track_points(last.gray, now.gray, tracks.px, p, guess)
        if before is not None:
            if flow.counts.kept <= before.flow.counts.kept:
                return replace(before, retry=True)
            return self._followed(side, now, tracks, flow, LK_STEREO, True)
        if 2 * flow.counts.kept >= len(tracks):
            return self._followed(side, now, tracks, flow, LK_PREDICTED, False)
        best, lk, retried = flow, LK_PREDICTED, False
        moved = np.linalg.norm(np.where(np.isfinite(guess), guess, tracks.px) - tracks.px, axis=1)
        if np.any(moved > 1.0):                         # (else zero motion is what was just tried)
            retried = True
            zero = track_points(last.gray, now.gray, tracks.px, p)
            if zero.counts.kept > best.counts.kept:
                best, lk = zero, LK_ZERO
        if 2 * best.counts.kept < len(tracks) and last.fixation_px is not None and now.fixation_px is not None \
                and last.fixation_id == now.fixation_id:
            shift = np.subtract(now.fixation_px, last.fixation_px)
            if float(np.hypot(*shift)) > 1.0:
                retried = True
                shifted = track_points(last.gray, now.gray, tracks.px, p, tracks.px + shift)
                if shifted.counts.kept > best.counts.kept:
                    best, lk = shifted, LK_FIXATION
        return self._followed(side, now, tracks, best, lk, retried)

    def _followed(self, side: str, now: CameraSample, tracks: Tracks, flow: PointFlow, lk: str, retry: bool) -> _Follow:
        ok = flow.ok
        rays = self.rig.pixels_to_rig_rays(side, flow.curr_px[ok], now.pan, now.tilt)
        fin = np.all(np.isfinite(rays), axis=1)
        counts = replace(flow.counts, lost=flow.counts.lost + int((~fin).sum()), kept=int(fin.sum()))
        old = tracks.select(ok)
        return _Follow(flow, Tracks(old.ids[fin], flow.curr_px[ok][fin], rays[fin]), counts, (old.rays[fin], rays[fin]),
                       lk, retry)

    def _register(self, side: str, now: CameraSample, tracks: Tracks, stamp: float, dt: float
                  ) -> tuple[Tracks, np.ndarray, np.ndarray, int]:
        """``tracks`` at t with the LK positions of those due (``FlowParams.register_period_s``) replaced by their
        birth patches' registrations (and the rays recomputed); a track whose birth patch no longer registers ends
        (:func:`~fixego_ros.tracking.flow.register` says why). Returns the tracks, their affines since birth, when each
        was last registered, and how many ended."""
        births = self._births[side]
        rows = None if births is None or not len(tracks) else births.rows(tracks.ids)
        if rows is None:          # (every track is born with a patch; a camera skipped at t-1 has no tracks)
            return tracks, np.repeat(np.eye(2)[None], len(tracks), axis=0), np.full(len(tracks), stamp), 0
        linear, stamps = births.linear[rows], births.stamps[rows]
        period, n = self.params.register_period_s, len(rows)
        # a share of the tracks per frame, the longest unregistered first: each about once per period, at an even cost
        due = n if period <= 0.0 or dt <= 0.0 else min(n, math.ceil(n * dt / period - 1e-9))
        now_due = np.sort(np.argsort(stamps, kind='stable')[:due])
        px, lin, done = register(now.gray, tracks.px[now_due], births.patches.take(rows[now_due]), linear[now_due])
        rays = self.rig.pixels_to_rig_rays(side, px, now.pan, now.tilt)
        done &= np.all(np.isfinite(rays), axis=1)
        out_px, out_rays, keep = tracks.px.copy(), tracks.rays.copy(), np.ones(n, bool)
        out_px[now_due], out_rays[now_due], linear[now_due] = px, rays, lin
        stamps[now_due] = stamp
        keep[now_due[~done]] = False
        return (Tracks(tracks.ids[keep], out_px[keep], out_rays[keep]), linear[keep], stamps[keep],
                int((~keep).sum()))

    def _keep_births(self, side: str, tracks: Tracks, followed: np.ndarray, linear: np.ndarray, registered: np.ndarray,
                     born: _Births | None) -> None:
        """Keep the birth patches of ``tracks``: those ``followed`` into t (their affines now ``linear``, last
        registered at ``registered``, in that order) that are still live, and those ``born`` at t. The others are
        forgotten."""
        old = self._births[side]
        parts = []
        ids = tracks.ids[np.isin(tracks.ids, followed)]
        rows = old.rows(ids) if old is not None and len(ids) else None
        if rows is not None:
            at = np.searchsorted(followed, ids)
            same = len(rows) == len(old.ids)       # every track went on: its patches as they are, not copied
            parts.append(_Births(ids, old.patches if same else old.patches.take(rows), linear[at], registered[at]))
        if born is not None:
            parts.append(born)
        self._births[side] = None if not parts else parts[0] if len(parts) == 1 else _Births(
            np.concatenate([b.ids for b in parts]), BirthPatches.concat([b.patches for b in parts]),
            np.concatenate([b.linear for b in parts]), np.concatenate([b.stamps for b in parts]))

    def _check(self, side: str, s: CameraSample | None, current: dict[str, CameraSample | None]) -> CameraFrame | None:
        """The camera's frame at t without flow (fixation ray, rotation), or None when the sample is unusable;
        ``current[side]`` becomes the checked sample (or None)."""
        current[side] = None
        if s is None:
            self._skip(side, MISSING, 'no sample')
            return None
        cam = self.rig.camera(side)
        img = s.gray
        if not isinstance(img, np.ndarray) or img.ndim != 2 or img.shape != (cam.height, cam.width) \
                or img.dtype != np.uint8:
            shape = getattr(img, 'shape', None)
            self._skip(side, BAD_IMAGE, f'image shape {shape} dtype {getattr(img, "dtype", None)}, rig camera '
                                        f'is {cam.height}x{cam.width} (HxW) uint8')
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
        current[side] = CameraSample(img, pan, tilt, fix_px, int(s.fixation_id) if fix_px is not None else -1)
        sigma = float(s.joint_sigma)
        return CameraFrame(ray, int(s.fixation_id) if ray is not None else -1, C,
                           joint_sigma=sigma if math.isfinite(sigma) and sigma > 0.0 else 0.0)

    def _finish(self, side: str, frame: CameraFrame, now: CameraSample, f: _Follow | None, stamp: float, dt: float
                ) -> CameraFrame:
        """Region, flow pairs keyframe -> t with the epipolar check, new tracks; fills ``frame``."""
        p = self.params
        cam = self.rig.camera(side)
        if f is not None:
            tracks, counts, lk, retry = f.tracks, f.counts, f.lk, f.retry
            tracks, linear, registered, unregistered = self._register(side, now, tracks, stamp, dt)
            counts = replace(counts, unregistered=unregistered, kept=counts.kept - unregistered)
        else:
            tracks, counts, lk, retry = Tracks(), FlowCounts(), '', False
            linear, registered = np.zeros((0, 2, 2)), np.zeros(0)
        followed = tracks.ids

        fix_px = now.fixation_px
        centre = fix_px if fix_px is not None else ((cam.width - 1) / 2.0, (cam.height - 1) / 2.0)
        region, keep_box, target = self._regions(centre, now.gray.shape)

        # 1. flow pairs keyframe -> t; epipolar outliers end
        key, prev = self._key[side], self._prev[side]
        ransac = False
        if prev is None:
            status, detail = NO_PREVIOUS, 'no usable sample at the keyframe'
            self.last_tracks[side] = None
        else:
            status, detail = OK, ''
            _, ia, ib = np.intersect1d(key.ids, tracks.ids, assume_unique=True, return_indices=True)
            a, b = key.rays[ia], tracks.rays[ib]
            if len(a) >= 8 and p.ransac_px > 0:
                out = epipolar_outliers(a, b, self.rig.cam_to_rig(side, prev.pan, prev.tilt), cam.fx, p.ransac_px,
                                        p.ransac_min_parallax_px)
                ransac = out is not None
                if out is not None and out.any():
                    n_out = int(out.sum())
                    counts = replace(counts, epipolar=n_out, kept=counts.kept - n_out)
                    dead = np.zeros(len(tracks), bool)
                    dead[ib[out]] = True
                    ia, ib, a, b = ia[~out], ib[~out], a[~out], b[~out]
                    tracks = tracks.select(~dead)
                    ib = _reindex(ib, dead)
            frame.flow_prev, frame.flow_curr = a, b
            if not len(a):
                detail = 'no track alive at both the keyframe and now' if len(key) else 'no tracks at the keyframe'
            self.last_tracks[side] = FlowTracks(key.px[ia], tracks.px[ib], counts, window=region, center_px=centre)

        # 2. tracks outside their region end (after giving their pair: the region moves when the fixation
        # point is re-selected, and the step keyframe -> t still needs their flow)
        keep = _in_box(tracks.px, keep_box)
        if not keep.all():
            n_out = int((~keep).sum())
            counts = replace(counts, outside=counts.outside + n_out, kept=counts.kept - n_out)
            tracks = tracks.select(keep)

        # 3. new tracks once the region lacks REPLENISH_FRACTION of the target (and the camera holds fewer than the
        #    target in all)
        need = min(target - int(_in_box(tracks.px, region).sum()), target - len(tracks))
        n_new, born = 0, None
        batch = max(1, round(REPLENISH_FRACTION * target))
        if need >= batch and region[2] - region[0] >= 1 and region[3] - region[1] >= 1:
            pts = detect_corners(now.gray, region, need, p, exclude=tracks.px)
            rays = self.rig.pixels_to_rig_rays(side, pts, now.pan, now.tilt)
            fin = np.all(np.isfinite(rays), axis=1)
            n_new = int(fin.sum())
            if n_new:
                ids = self._next_id[side] + np.arange(n_new, dtype=np.int64)
                self._next_id[side] += n_new
                tracks = tracks.plus(Tracks(ids, pts[fin], rays[fin]))
                born = _Births(ids, birth_patches(now.gray, pts[fin]), np.repeat(np.eye(2)[None], n_new, axis=0),
                               np.full(n_new, stamp))
        counts = replace(counts, new=n_new)
        self._keep_births(side, tracks, followed, linear, registered, born)
        if self.last_tracks[side] is not None:
            self.last_tracks[side] = replace(self.last_tracks[side], counts=counts)

        frame.track_ids, frame.track_rays = tracks.ids.copy(), tracks.rays.copy()
        self._tracks[side], self._last[side] = tracks, now
        self.last[side] = SideReport(status, detail, counts, len(frame.flow_prev), frame.fixation_ray is not None,
                                     region, len(tracks), lk, retry, ransac)
        return frame


@dataclass(frozen=True)
class _Follow:
    """One camera's tracks followed from the previous frame into t."""

    flow: PointFlow
    tracks: Tracks                              # the survivors at t
    counts: FlowCounts
    step: tuple[np.ndarray, np.ndarray]         # their rays at t-1 and at t (rig frames)
    lk: str
    retry: bool


def _reindex(idx: np.ndarray, dead: np.ndarray) -> np.ndarray:
    """Indices ``idx`` into an array from which the ``dead`` entries were removed (``idx`` not dead)."""
    return idx - np.cumsum(dead)[idx]
