"""Fixation point selection and tracking on grey images (ROS-free; also used offline by the replay).

A fixation point is a well-textured static scene point that the servo keeps at the image centre.
Selection picks the strongest corner (minimum eigenvalue of the structure tensor) near a preferred
pixel, weighted towards it. Tracking is pyramidal Lucas-Kanade with two validity checks: the
forward-backward error and the normalised cross-correlation against the template taken at selection
(so slow drift onto another structure is caught); where it holds, the position is the template registered there
with an affine warp (:func:`~fixego_ros.tracking.flow.register`: LK alone drifts off the point as the scene comes
closer, and the fixation point is the longest track of all). When Lucas-Kanade loses the point (a jump larger
than its pyramid follows: a head that lags the rig at a low frame rate moves the point tens of pixels
between frames), the template is searched for around the last pixel and, when found unambiguously,
Lucas-Kanade refines it from there: the same point keeps its id. A new point, with a new id, is selected
only when that fails too, the point nears the image border, or the caller asks (manual, or after the head swung
back from a limit: :class:`LimitCheck`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from fixego_ros.geometry.rig import CameraModel
from fixego_ros.tracking.flow import BirthPatches, birth_patches, register

# the fixation id of "no valid fixation": before the first selection, and on the fixation topic for a frame without
# one (camera_node publishes one message per image; a valid id is >= 0)
NO_FIXATION_ID = -1


@dataclass
class FixationParams:
    search_radius_px: float = 60.0     # selection window radius around the preferred pixel
    min_corner_score: float = 2e-4     # min-eigenvalue score (image scaled to 0..1) a point must reach
    corner_block: int = 7
    template_half: int = 10            # template is (2h+1)^2 px
    lk_win: int = 21
    lk_levels: int = 3
    fb_max_px: float = 1.0             # forward-backward error bound
    ncc_min: float = 0.7               # template correlation bound
    border_margin_px: float = 40.0     # re-select when the point comes this close to the border
    max_age_s: float = 0.0             # > 0: re-select points older than this
    relocate_radius_px: float = 400.0  # template search radius around the last pixel when LK loses it; 0 = off
    relocate_margin: float = 0.1       # the best match must beat any other place by this much NCC (no twins)


@dataclass(frozen=True)
class FixationState:
    pixel: tuple[float, float] | None  # (u, v) in the raw image, None when there is no valid fixation
    fixation_id: int                   # increments on each re-selection; -1 before the first
    quality: float                     # template NCC in [-1, 1] (1 at selection)
    reselected: bool                   # this frame started a new fixation
    reason: str                        # why it was (re)selected or why it is invalid; '' when tracking
    stamp: float
    age_s: float = 0.0

    @property
    def valid(self) -> bool:
        return self.pixel is not None


@dataclass
class _Track:
    pixel: np.ndarray
    template: np.ndarray
    fixation_id: int
    t_selected: float
    birth: BirthPatches         # the template as :func:`~fixego_ros.tracking.flow.register` aligns it
    linear: np.ndarray = field(default_factory=lambda: np.eye(2)[None])   # its affine since the selection


@dataclass
class Reselection:
    stamp: float
    fixation_id: int
    reason: str
    pixel: tuple[float, float]


class FixationTracker:
    """Feed grey frames in order with :meth:`update`; call :meth:`request_reselect` to force a new point."""

    def __init__(self, camera: CameraModel, params: FixationParams | None = None) -> None:
        self.camera = camera
        self.params = params or FixationParams()
        self._prev: np.ndarray | None = None
        self._track: _Track | None = None
        self._next_id = 0
        self._request: tuple[str, tuple[float, float]] | None = None
        self.reselections: list[Reselection] = []
        self.last: FixationState | None = None

    @property
    def fixation_id(self) -> int:
        return self._track.fixation_id if self._track else self._next_id - 1

    def request_reselect(self, reason: str = 'manual', offset_px: tuple[float, float] = (0.0, 0.0)) -> None:
        """Select a new point on the next frame, near the centre plus ``offset_px``."""
        self._request = (reason, (float(offset_px[0]), float(offset_px[1])))

    def reselect_last(self, pixel: tuple[float, float], reason: str = 'external') -> bool:
        """Start a new fixation at ``pixel`` of the last image seen, which the next :meth:`update` follows on
        (replay: a vergence measurement of that image's frame shows where the head's point is). False, with no
        change, when there is no image yet or the pixel is too close to the border."""
        if self._prev is None or self.last is None:
            return False
        before = (self._track, self.last)
        state = self.select_at(self._prev, pixel, self.last.stamp, reason)
        if not state.valid:
            self._track, self.last = before
        return state.valid

    def reset(self) -> None:
        self._prev, self._track, self._request = None, None, None

    def select_at(self, gray: np.ndarray, pixel: tuple[float, float], stamp: float,
                  reason: str = 'external') -> FixationState:
        """Start a new fixation (new id) at ``pixel`` of this frame instead of :meth:`update` for it, e.g. at a
        point matched in the other camera (start-up vergence). Invalid (no change of id) when the pixel is
        too close to the border for its template."""
        gray = self._gray(gray)
        p = self.params
        px = np.asarray(pixel, dtype=np.float64).reshape(2)
        template = self._patch(gray, px) if np.all(np.isfinite(px)) and not self._near_border(px) else None
        self._request = None
        if template is None:
            self._track = None
            state = FixationState(None, self.fixation_id, 0.0, False, 'outside', float(stamp))
        else:
            fid = self._next_id
            self._next_id += 1
            self._track = _Track(px, template, fid, float(stamp), birth_patches(gray, px[None], p.template_half))
            self.reselections.append(Reselection(float(stamp), fid, reason, (float(px[0]), float(px[1]))))
            state = FixationState((float(px[0]), float(px[1])), fid, 1.0, True, reason, float(stamp), 0.0)
        self._prev = gray
        self.last = state
        return state

    # ------------------------------------------------------------------------------------------------
    @staticmethod
    def _gray(gray: np.ndarray) -> np.ndarray:
        gray = np.ascontiguousarray(gray if gray.ndim == 2 else cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY))
        return gray if gray.dtype == np.uint8 else np.clip(gray, 0, 255).astype(np.uint8)

    def update(self, gray: np.ndarray, stamp: float) -> FixationState:
        gray = self._gray(gray)
        state = self._update(gray, float(stamp))
        self._prev = gray
        self.last = state
        return state

    def _update(self, gray: np.ndarray, stamp: float) -> FixationState:
        p = self.params
        if self._request is not None:
            reason, offset = self._request
            self._request = None
            return self._select(gray, stamp, reason, offset)
        if self._track is None or self._prev is None or self._prev.shape != gray.shape:
            return self._select(gray, stamp, 'initial' if self._next_id == 0 else 'lost')
        ok, pixel, quality, why = self._follow(gray)
        if ok and not self._near_border(pixel):
            if p.max_age_s > 0 and stamp - self._track.t_selected > p.max_age_s:
                return self._select(gray, stamp, 'max_age')
            # the template registered where LK put it: LK alone drifts off the point (0.3-0.6 px after 16-32
            # frames on the papers' loop, the fixation being the longest track of all; 0.02-0.06 px registered);
            # where it does not register, LK's position (the template check above still holds it)
            tr = self._track
            at, linear, registered = register(gray, pixel[None], tr.birth, tr.linear)
            if registered[0] and not self._near_border(at[0]):
                pixel, tr.linear = at[0], linear
            self._track.pixel = pixel
            return FixationState((float(pixel[0]), float(pixel[1])), self._track.fixation_id, quality, False, '',
                                 stamp, stamp - self._track.t_selected)
        return self._select(gray, stamp, why if not ok else 'left_image')

    def _near_border(self, px: np.ndarray) -> bool:
        m = self.params.border_margin_px
        h, w = self.camera.height, self.camera.width
        return bool(px[0] < m or px[1] < m or px[0] > w - 1 - m or px[1] > h - 1 - m)

    def _patch(self, gray: np.ndarray, px: np.ndarray) -> np.ndarray | None:
        h = self.params.template_half
        size = 2 * h + 1
        if (px[0] < h + 1 or px[1] < h + 1 or px[0] > gray.shape[1] - h - 2 or px[1] > gray.shape[0] - h - 2):
            return None
        return cv2.getRectSubPix(gray, (size, size), (float(px[0]), float(px[1]))).astype(np.float32)

    @staticmethod
    def _ncc(a: np.ndarray, b: np.ndarray) -> float:
        a = a - a.mean()
        b = b - b.mean()
        den = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
        return float((a * b).sum() / den) if den > 1e-9 else 0.0

    def _follow(self, gray: np.ndarray) -> tuple[bool, np.ndarray, float, str]:
        """LK from the last pixel; when that fails, LK from where the template is found nearby."""
        found = self._lk_check(gray, None)
        if found[0] or self.params.relocate_radius_px <= 0:
            return found
        guess = self._relocate(gray)
        return found if guess is None else self._lk_check(gray, guess)

    def _lk_check(self, gray: np.ndarray, guess: np.ndarray | None) -> tuple[bool, np.ndarray, float, str]:
        """LK of the fixation point (from ``guess`` when given) with the forward-backward and template checks."""
        p, tr = self.params, self._track
        assert tr is not None and self._prev is not None
        lk = {'winSize': (p.lk_win, p.lk_win), 'maxLevel': p.lk_levels,
              'criteria': (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)}
        p0 = tr.pixel.reshape(1, 1, 2).astype(np.float32)
        if guess is None:
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev, gray, p0, None, **lk)
        else:
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev, gray, p0, guess.reshape(1, 1, 2).astype(np.float32),
                                                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        if p1 is None or not st1[0, 0]:
            return False, tr.pixel, 0.0, 'lost'
        if guess is None:       # backward from where forward ended, as LK alone would
            back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self._prev, p1, None, **lk)
        else:                   # backward: the template's jump undone, LK's own refinement left to check
            start = (p1 - (guess.reshape(1, 1, 2) - p0)).astype(np.float32)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self._prev, p1, start, flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                                    **lk)
        if back is None or not st2[0, 0] or float(np.linalg.norm(back - p0)) > p.fb_max_px:
            return False, tr.pixel, 0.0, 'lost'
        px = p1.reshape(2).astype(np.float64)
        patch = self._patch(gray, px)
        if patch is None:
            return False, px, 0.0, 'left_image'
        q = self._ncc(tr.template, patch)
        if q < p.ncc_min:
            return False, px, q, 'lost'
        return True, px, q, ''

    def _relocate(self, gray: np.ndarray) -> np.ndarray | None:
        """Where the template matches best within ``relocate_radius_px`` of the last pixel, or None when the
        best match is below ``ncc_min`` or another place (beyond the template's size) matches nearly as well."""
        p, tr = self.params, self._track
        assert tr is not None
        h = p.template_half
        r = p.relocate_radius_px
        x0, y0 = int(max(0, math.floor(tr.pixel[0] - r - h))), int(max(0, math.floor(tr.pixel[1] - r - h)))
        x1 = int(min(gray.shape[1], math.ceil(tr.pixel[0] + r + h + 1)))
        y1 = int(min(gray.shape[0], math.ceil(tr.pixel[1] + r + h + 1)))
        if x1 - x0 <= 2 * h + 1 or y1 - y0 <= 2 * h + 1:
            return None
        score = cv2.matchTemplate(gray[y0:y1, x0:x1].astype(np.float32), tr.template, cv2.TM_CCOEFF_NORMED)
        score = np.nan_to_num(score, nan=-1.0)
        iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
        best = float(score[iy, ix])
        if best < p.ncc_min:
            return None
        others = score.copy()
        others[max(0, iy - 2 * h):iy + 2 * h + 1, max(0, ix - 2 * h):ix + 2 * h + 1] = -1.0
        if float(others.max()) > best - p.relocate_margin:
            return None
        return np.array([x0 + ix + h, y0 + iy + h], dtype=np.float64)

    def _select(self, gray: np.ndarray, stamp: float, reason: str,
                offset: tuple[float, float] = (0.0, 0.0)) -> FixationState:
        p = self.params
        cam = self.camera
        h, w = gray.shape
        m = max(p.border_margin_px, p.template_half + 2)
        cx = min(max(cam.cx + offset[0], m), w - 1 - m)
        cy = min(max(cam.cy + offset[1], m), h - 1 - m)
        r = p.search_radius_px
        x0, x1 = int(max(m, cx - r)), int(min(w - m, cx + r + 1))
        y0, y1 = int(max(m, cy - r)), int(min(h - m, cy + r + 1))
        self._track = None
        if x1 - x0 < 3 or y1 - y0 < 3:
            return FixationState(None, self.fixation_id, 0.0, False, 'no_texture', stamp)
        pad = p.corner_block
        roi = gray[max(0, y0 - pad):y1 + pad, max(0, x0 - pad):x1 + pad].astype(np.float32) / 255.0
        score = cv2.cornerMinEigenVal(roi, p.corner_block, 3)
        oy, ox = y0 - max(0, y0 - pad), x0 - max(0, x0 - pad)
        score = score[oy:oy + (y1 - y0), ox:ox + (x1 - x0)]
        yy, xx = np.mgrid[y0:y1, x0:x1]
        weight = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2.0 * (0.5 * r) ** 2))
        weighted = score * weight
        iy, ix = np.unravel_index(int(np.argmax(weighted)), weighted.shape)
        if score[iy, ix] < p.min_corner_score:
            return FixationState(None, self.fixation_id, 0.0, False, 'no_texture', stamp)
        pt = np.array([[[x0 + ix, y0 + iy]]], dtype=np.float32)
        cv2.cornerSubPix(gray, pt, (3, 3), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.01))
        px = pt.reshape(2).astype(np.float64)
        template = self._patch(gray, px)
        if template is None:
            return FixationState(None, self.fixation_id, 0.0, False, 'no_texture', stamp)
        fid = self._next_id
        self._next_id += 1
        self._track = _Track(px, template, fid, stamp, birth_patches(gray, px[None], p.template_half))
        pixel = (float(px[0]), float(px[1]))
        self.reselections.append(Reselection(stamp, fid, reason, pixel))
        return FixationState(pixel, fid, 1.0, True, reason, stamp, 0.0)


@dataclass
class LimitCheck:
    """Decides when pan/tilt is close enough to a limit that the head should swing back, and to which device
    angles: ``swing_rad`` towards the middle of that axis's range, not past the middle. The new fixation point is
    chosen at the image centre once the head is there. A point chosen inside the current image cannot do this: it
    needs the head within a few degrees of where it is, still inside the margin, so on the papers' loop (the rig
    turning 28 deg/s for 7 s) the head stayed pinned at its limit for the rest of the run."""

    pan_range_rad: tuple[float, float]
    tilt_range_rad: tuple[float, float]
    margin_rad: float = math.radians(5.0)
    swing_rad: float = math.radians(60.0)
    armed: dict[str, bool] = field(default_factory=lambda: {'pan': True, 'tilt': True})

    def _axis(self, angle: float, limits: tuple[float, float]) -> float | None:
        """The angle to swing this axis to, or None when it is clear of its margins."""
        lo, hi = limits
        mid = 0.5 * (lo + hi)
        if angle > hi - self.margin_rad:
            return angle - min(self.swing_rad, max(angle - mid, 0.0))
        if angle < lo + self.margin_rad:
            return angle + min(self.swing_rad, max(mid - angle, 0.0))
        return None

    def due(self, pan: float, tilt: float) -> bool:
        """Whether :meth:`check` would fire now (no state changes: a swing that waits stays armed)."""
        return ((self._axis(pan, self.pan_range_rad) is not None and self.armed['pan'])
                or (self._axis(tilt, self.tilt_range_rad) is not None and self.armed['tilt']))

    def check(self, pan: float, tilt: float) -> tuple[float, float] | None:
        """Device angles (pan, tilt) to swing the head to, or None. Fires once per approach: an axis re-arms only
        once it is clear of its margin again."""
        fire = self.due(pan, tilt)
        aim_pan = self._axis(pan, self.pan_range_rad)
        aim_tilt = self._axis(tilt, self.tilt_range_rad)
        self.armed['pan'] = aim_pan is None
        self.armed['tilt'] = aim_tilt is None
        if not fire:
            return None
        return (pan if aim_pan is None else aim_pan, tilt if aim_tilt is None else aim_tilt)


@dataclass
class SwingStagger:
    """Keeps the two heads from swinging back from their limits at the same time. A head whose swing is due waits
    while the other camera's latest fixation message says "no valid fixation" (it is swinging itself, has lost its
    point, or a vergence step drives it), for at most ``max_hold_s``; meanwhile it goes on fixating (pinned at its
    limit, the tracker re-selects as the point nears the border). Why: while both heads swing neither camera has a
    fixation and every track is new, so the estimator has no rays to place those frames with. On the papers' loop
    both heads reached their limits within frames of each other at the end of each arc: 3-4 such gaps of 0.1-0.8 s
    per recorded run.

    Both heads can reach a limit at the same image stamp, each seeing the other still fixating. The head with
    ``wait_for_partner_frame`` (the left) breaks the tie: it also waits until the other's message for this frame
    (a stamp within half a frame of its own, or later) is in. A partner that never published is not waited for."""

    max_hold_s: float = 1.0
    wait_for_partner_frame: bool = False
    holds: int = 0                                   # swings that waited for the other head (once per approach)
    _partner: tuple[float, bool] | None = None       # the partner's newest message: stamp, has a fixation
    _since: float | None = None                      # image stamp when the current wait began
    _counted: bool = False                           # this wait is in ``holds``

    def on_partner(self, stamp: float, has_fixation: bool) -> None:
        """The other camera's fixation message (the newest by stamp counts; late arrivals are ignored)."""
        if self._partner is None or stamp >= self._partner[0]:
            self._partner = (stamp, has_fixation)

    @property
    def partner_fixated(self) -> bool:
        """Whether the other camera's newest fixation message has a fixation (True before any came)."""
        return self._partner is None or self._partner[1]

    def hold(self, t: float, frame_s: float) -> bool:
        """Whether a swing due at image stamp ``t`` waits (``frame_s``: this camera's frame interval)."""
        if self.max_hold_s <= 0.0 or self._partner is None:
            return False
        stamp, has_fixation = self._partner
        behind = self.wait_for_partner_frame and stamp < t - 0.5 * frame_s
        if has_fixation and not behind:
            return False
        if self._since is None:
            self._since = t
        if not has_fixation and not self._counted:
            self._counted = True
            self.holds += 1
        return t - self._since <= self.max_hold_s

    def reset(self) -> None:
        """The swing started (or is no longer due): the next one waits afresh."""
        self._since = None
        self._counted = False
