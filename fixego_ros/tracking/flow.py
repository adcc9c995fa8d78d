"""Sparse optical flow around a fixation point (ROS-free): corners in a window, pyramidal LK, checks.

The coplanarity constraints of DESIGN.md §5 need, per camera, pixels at t-1 and the same scene points
at t. Corners (minimum-eigenvalue, ``cv2.goodFeaturesToTrack``) are detected in the previous image
inside a square window centred on the previous fixation pixel, tracked forward with pyramidal
Lucas-Kanade, and kept only if

- LK converged and the structure tensor's minimum eigenvalue reaches ``min_eig`` (OpenCV's
  ``minEigThreshold`` with ``OPTFLOW_LK_GET_MIN_EIGENVALS``: flat patches give unreliable flow),
- the point lands inside the image minus ``border_px``,
- tracking it back from t lands within ``fb_max_px`` of where it started (forward-backward check:
  catches most occlusions, repeated texture and points that drifted onto another structure),
- the patches around the two ends correlate (normalised cross-correlation >= ``ncc_min``). The
  forward-backward check alone is not enough: where the content at t is unrelated to t-1 (occlusion,
  specular change) LK settles in a local minimum of the new texture, and tracking back from there
  settles in the mirror minimum, so ~10 % of such tracks pass it with errors of several pixels.

One way to track points: :func:`track_points` runs the checks above on given points, optionally from
predicted positions (``OPTFLOW_USE_INITIAL_FLOW``: LK starts at the guess instead of at the point, and
the backward pass starts at the point plus the same error, so the forward-backward check keeps its
meaning). :func:`track_flow` detects corners in a window and tracks them (two-frame flow); the stereo
front end keeps persistent tracks and calls :func:`track_points` frame to frame, then :func:`register`s each
track's birth patch (:func:`birth_patches`) at LK's position with an affine warp, which does not drift.

Presets: ``window`` (default) takes as many good corners as the ``window_px`` square offers, which the
Cramér-Rao analysis of DESIGN.md §5 shows the translation needs; ``paper`` takes the papers'
``paper_points`` strongest corners in the central ``paper_region_px`` square; ``full`` takes corners over
the whole image. For ``window``/``paper`` detection and LK run on crops around the window (not the whole
image), which is what keeps a camera's flow around a millisecond.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import cv2
import numpy as np

PRESETS = ('paper', 'window', 'full')
_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)  # as the fixation tracker
_CORNER_BLOCK = 3   # goodFeaturesToTrack's default structure-tensor block
_PAD = _CORNER_BLOCK // 2 + 2  # context kept around a detection box so its corners see real pixels


@dataclass(frozen=True)
class FlowParams:
    """How flow points are chosen and which tracks are trusted (defaults: the papers' real set-up)."""

    preset: str = 'full'            # 'paper' | 'window' | 'full'
    window_px: int = 100            # side of the flow window centred on the fixation pixel
    paper_region_px: int = 30       # 'paper': central square of the window the points come from
    paper_points: int = 3           # 'paper': how many points
    max_corners: int = 80           # 'window' / 'full': at most this many points
    corner_quality: float = 0.01    # goodFeaturesToTrack qualityLevel (relative to the best corner)
    min_distance_px: float = 6.0    # minimum distance between detected corners
    lk_win: int = 21                # LK window side (px)
    lk_levels: int = 3              # LK pyramid levels above the base image
    min_eig: float = 1e-3           # LK minEigThreshold: reject flat patches
    fb_max_px: float = 0.5          # forward-backward consistency bound
    ncc_min: float = 0.8            # patch correlation bound between the two ends (<= -1 disables)
    ncc_half: int = 5               # correlation patch is (2h+1)^2 px
    border_px: int = 8              # points must stay this far inside the image
    ransac_px: float = 1.0          # front end: epipolar RANSAC inlier bound (px at the focal length; <= 0: off)
    ransac_min_parallax_px: float = 0.5  # front end: skip RANSAC below this median rotation-compensated parallax
    register_period_s: float = 0.1  # front end: each track's birth patch registered about this often (0: every frame)

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f'FlowParams.preset must be one of {PRESETS}, got {self.preset!r}')
        ints = {'window_px': 4, 'paper_region_px': 1, 'paper_points': 1, 'max_corners': 1, 'lk_win': 3,
                'lk_levels': 0, 'border_px': 0, 'ncc_half': 1}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ints:
                if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < ints[f.name]:
                    raise ValueError(f'FlowParams.{f.name} must be an integer >= {ints[f.name]}, got {value!r}')
            elif f.name != 'preset' and (isinstance(value, bool) or not isinstance(value, (int, float))
                                         or not math.isfinite(value)):
                raise ValueError(f'FlowParams.{f.name} must be a finite number, got {value!r}')
        if self.max_corners > 20000:   # cv2.remap maps (correlation patches) are limited to 32767 rows
            raise ValueError(f'FlowParams.max_corners must be <= 20000, got {self.max_corners}')
        if self.lk_levels > 8:
            raise ValueError(f'FlowParams.lk_levels must be <= 8, got {self.lk_levels}')
        if self.paper_region_px > self.window_px:
            raise ValueError(f'FlowParams.paper_region_px ({self.paper_region_px}) must be <= window_px '
                             f'({self.window_px}): the paper region lies inside the flow window')
        if not 0.0 < self.corner_quality < 1.0:
            raise ValueError(f'FlowParams.corner_quality must be in (0, 1), got {self.corner_quality}')
        if self.min_distance_px < 0.0:
            raise ValueError(f'FlowParams.min_distance_px must be >= 0, got {self.min_distance_px}')
        if self.min_eig < 0.0:
            raise ValueError(f'FlowParams.min_eig must be >= 0, got {self.min_eig}')
        if self.fb_max_px <= 0.0:
            raise ValueError(f'FlowParams.fb_max_px must be > 0, got {self.fb_max_px}')
        if self.ncc_min > 1.0:
            raise ValueError(f'FlowParams.ncc_min must be <= 1, got {self.ncc_min}')
        if self.register_period_s < 0.0:
            raise ValueError(f'FlowParams.register_period_s must be >= 0, got {self.register_period_s}')
        if self.ransac_min_parallax_px < 0.0:
            raise ValueError(f'FlowParams.ransac_min_parallax_px must be >= 0, got {self.ransac_min_parallax_px}')

    @property
    def lk_margin_px(self) -> int:
        """Context around the window that LK's coarsest level can reach (crop margin)."""
        return self.lk_win * 2**self.lk_levels // 2 + self.lk_win


@dataclass(frozen=True)
class FlowCounts:
    """Where the tracked points went:
    ``detected = lost + min_eig + outside + fb + ncc + epipolar + unregistered + kept``.

    ``detected`` is the number of points tracked into frame t: the corners detected at t-1 for
    :func:`track_flow`, the live tracks of t-1 for the stereo front end (whose corners newly detected at t
    are counted in ``new``, outside the sum: they are tracked from the next frame on)."""

    detected: int = 0
    lost: int = 0        # LK did not converge (forward or backward), or the point has no finite ray
    min_eig: int = 0     # patch too flat (forward at t-1 or backward at t)
    outside: int = 0     # landed outside the image minus the border (front end: or left the track region)
    fb: int = 0          # forward-backward error above the bound
    ncc: int = 0         # patches at t-1 and t do not correlate
    epipolar: int = 0    # front end: outlier of the camera's epipolar (essential) model keyframe -> t
    unregistered: int = 0   # front end: its birth patch no longer registers (:func:`register`): not one static point
    kept: int = 0
    new: int = 0         # front end: corners detected at t that start new tracks (not in the sum)

    def as_dict(self) -> dict[str, int]:
        return {f.name: int(getattr(self, f.name)) for f in fields(self)}

    def __add__(self, other: FlowCounts) -> FlowCounts:
        return FlowCounts(**{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)})


Box = tuple[int, int, int, int]  # x0, y0, x1, y1 (half-open pixel ranges)


@dataclass(frozen=True)
class FlowTracks:
    """Tracked points: ``prev_px[i]`` at t-1 is ``curr_px[i]`` at t; ``reason`` is '' unless nothing was tried."""

    prev_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))   # (N, 2) float64
    curr_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))   # (N, 2) float64
    counts: FlowCounts = field(default_factory=FlowCounts)
    reason: str = ''                 # why no points were tracked ('' when tracking ran)
    window: Box | None = None        # detection box in the previous image
    center_px: tuple[float, float] | None = None  # window centre actually used

    def __len__(self) -> int:
        return len(self.prev_px)


def _image_problem(img: object, name: str) -> str:
    if img is None:
        return f'{name} image missing'
    if not isinstance(img, np.ndarray) or img.ndim != 2:
        return f'{name} image is not a 2-D grey image'
    if img.size == 0:
        return f'{name} image is empty'
    if img.dtype != np.uint8:
        return f'{name} image is {img.dtype}, not uint8'
    return ''


def square_box(cx: float, cy: float, side: int, limits: Box) -> Box:
    """Square of ``side`` px centred on (cx, cy), clipped to ``limits``."""
    x0 = math.floor(cx - side / 2.0 + 0.5)
    y0 = math.floor(cy - side / 2.0 + 0.5)
    lx0, ly0, lx1, ly1 = limits
    return max(x0, lx0), max(y0, ly0), min(x0 + side, lx1), min(y0 + side, ly1)


def _grow(box: Box, margin: int, w: int, h: int) -> Box:
    x0, y0, x1, y1 = box
    return max(x0 - margin, 0), max(y0 - margin, 0), min(x1 + margin, w), min(y1 + margin, h)


def detect_corners(gray: np.ndarray, box: Box, max_corners: int, params: FlowParams,
                   exclude: np.ndarray | None = None) -> np.ndarray:
    """Strongest min-eigenvalue corners (N, 2) inside ``box``, strongest first, at least
    ``min_distance_px`` apart (and that far from every point of ``exclude``, (M, 2)). Only a crop of the
    box (plus a few px of context) is processed."""
    h, w = gray.shape
    cx0, cy0, cx1, cy1 = _grow(box, _PAD, w, h)
    roi = gray[cy0:cy1, cx0:cx1]
    mask = np.zeros(roi.shape, np.uint8)
    x0, y0, x1, y1 = box
    mask[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0] = 255
    near = np.zeros((0, 2))
    if exclude is not None and len(exclude):
        near = np.asarray(exclude, np.float64).reshape(-1, 2)
        r = params.min_distance_px
        near = near[(near[:, 0] > x0 - r) & (near[:, 0] < x1 + r) & (near[:, 1] > y0 - r) & (near[:, 1] < y1 + r)]
    # ask for enough to drop those too close to an excluded point (goodFeaturesToTrack keeps them apart)
    c = cv2.goodFeaturesToTrack(roi, int(max_corners) + len(near), float(params.corner_quality),
                                float(params.min_distance_px), mask=mask, blockSize=_CORNER_BLOCK)
    if c is None:
        return np.zeros((0, 2))
    pts = c.reshape(-1, 2).astype(np.float64) + (cx0, cy0)
    if len(near):
        d2 = ((pts[:, None, :] - near[None, :, :]) ** 2).sum(axis=2).min(axis=1)
        pts = pts[d2 >= params.min_distance_px**2]
    return pts[:int(max_corners)]


def track_flow(prev_gray: np.ndarray, curr_gray: np.ndarray, center_px: tuple[float, float] | None = None,
               params: FlowParams | None = None) -> FlowTracks:
    """Track corners around ``center_px`` (in ``prev_gray``; None = image centre) into ``curr_gray``.

    Never raises on bad input and never returns NaN: unusable images give zero points and a ``reason``.
    """
    p = params or FlowParams()
    why = _image_problem(prev_gray, 'previous') or _image_problem(curr_gray, 'current')
    if not why and prev_gray.shape != curr_gray.shape:
        why = f'image size changed: {prev_gray.shape[1]}x{prev_gray.shape[0]} -> ' \
              f'{curr_gray.shape[1]}x{curr_gray.shape[0]}'
    if why:
        return FlowTracks(reason=why)
    h, w = prev_gray.shape
    b = p.border_px
    valid: Box = (b, b, w - b, h - b)
    if valid[2] - valid[0] < 2 or valid[3] - valid[1] < 2:
        return FlowTracks(reason=f'image {w}x{h} too small for a {b} px border')
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    if p.preset == 'full':
        box, crop = valid, (0, 0, w, h)
        pts = detect_corners(prev_gray, box, p.max_corners, p)
    else:
        if center_px is not None:
            try:
                cx, cy = float(center_px[0]), float(center_px[1])
            except (TypeError, ValueError, IndexError):
                cx = cy = math.nan
            if not (math.isfinite(cx) and math.isfinite(cy)):
                return FlowTracks(reason=f'window centre is not a finite pixel: {center_px!r}')
        box = square_box(cx, cy, p.window_px, valid)
        region = square_box(cx, cy, p.paper_region_px, box) if p.preset == 'paper' else box
        if region[2] - region[0] < 1 or region[3] - region[1] < 1:
            return FlowTracks(reason=f'flow window around ({cx:.1f}, {cy:.1f}) is outside the image',
                              window=box, center_px=(cx, cy))
        crop = _grow(box, p.lk_margin_px, w, h)
        pts = detect_corners(prev_gray, region, p.paper_points if p.preset == 'paper' else p.max_corners, p)
    if len(pts) == 0:
        return FlowTracks(reason='no corners in the flow window', window=box, center_px=(cx, cy))
    tracked = track_points(prev_gray, curr_gray, pts, p, crop=crop)
    return FlowTracks(pts[tracked.ok], tracked.curr_px[tracked.ok], tracked.counts, window=box, center_px=(cx, cy))


@dataclass(frozen=True)
class PointFlow:
    """Result of :func:`track_points`: where each input point went (``curr_px[i]``, meaningful where
    ``ok[i]``), and the counts of the checks."""

    curr_px: np.ndarray    # (N, 2) float64
    ok: np.ndarray         # (N,) bool: passed every check
    counts: FlowCounts


def valid_box(shape: tuple[int, ...], border_px: int) -> Box:
    """Where tracked points must land: the image minus the border."""
    h, w = shape[:2]
    return border_px, border_px, w - border_px, h - border_px


def track_points(prev: np.ndarray, curr: np.ndarray, pts: np.ndarray, p: FlowParams,
                 guess: np.ndarray | None = None, crop: Box | None = None) -> PointFlow:
    """Track ``pts`` (N, 2) from ``prev`` into ``curr`` (same-size uint8 images): forward LK (from ``guess``,
    the predicted positions in ``curr``, when given), border check, backward LK with the forward-backward
    bound, then patch correlation. LK runs on the same crop of both images (pyramids of the crop only):
    ``crop`` (None = the points' and guesses' bounding box grown by the LK margin)."""
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    n = len(pts)
    if n == 0:
        return PointFlow(np.zeros((0, 2)), np.zeros(0, bool), FlowCounts())
    h, w = prev.shape
    valid = valid_box(prev.shape, p.border_px)
    g = pts if guess is None else np.where(np.isfinite(guess), guess, pts).reshape(-1, 2)
    if crop is None:
        both = np.concatenate([pts, g])
        lo, hi = np.floor(both.min(axis=0)), np.ceil(both.max(axis=0)) + 1
        crop = _grow((int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])), p.lk_margin_px, w, h)
    x0, y0, x1, y1 = crop
    A, B = prev[y0:y1, x0:x1], curr[y0:y1, x0:x1]
    off = np.array([x0, y0], dtype=np.float64)
    lk = {'winSize': (p.lk_win, p.lk_win), 'maxLevel': p.lk_levels, 'criteria': _CRITERIA,
          'flags': cv2.OPTFLOW_LK_GET_MIN_EIGENVALS | cv2.OPTFLOW_USE_INITIAL_FLOW, 'minEigThreshold': float(p.min_eig)}
    p0 = (pts - off).astype(np.float32).reshape(-1, 1, 2)
    g0 = (g - off).astype(np.float32).reshape(-1, 1, 2)
    p1, st, err = cv2.calcOpticalFlowPyrLK(A, B, p0, g0.copy(), **lk)
    st, err = st.ravel().astype(bool), err.ravel()
    q1 = p1.reshape(-1, 2).astype(np.float64) + off
    finite = np.all(np.isfinite(q1), axis=1)
    # with GET_MIN_EIGENVALS, err holds the min eigenvalue at t-1, so a failed status splits into the two
    weak = ~st & (err < p.min_eig)
    lost = (~st & ~weak) | (st & ~finite)
    ok = st & finite
    inside = ok & (q1[:, 0] >= valid[0]) & (q1[:, 1] >= valid[1]) \
        & (q1[:, 0] <= valid[2] - 1) & (q1[:, 1] <= valid[3] - 1)
    outside = ok & ~inside
    n_lost, n_weak = int(lost.sum()), int(weak.sum())
    n_fb, n_ncc, kept = 0, 0, np.zeros(n, bool)
    idx = np.flatnonzero(inside)
    if len(idx):
        # backward from where the point landed, offset by the prediction (start = point + forward error)
        back0 = (p1[idx] - (g0[idx] - p0[idx])).astype(np.float32)
        back, st2, err2 = cv2.calcOpticalFlowPyrLK(B, A, p1[idx], back0, **lk)
        st2, err2 = st2.ravel().astype(bool), err2.ravel()
        fb = np.linalg.norm(back.reshape(-1, 2).astype(np.float64) - p0[idx].reshape(-1, 2), axis=1)
        weak2 = ~st2 & (err2 < p.min_eig)
        good = st2 & (fb <= p.fb_max_px)        # NaN fails the comparison
        n_weak += int(weak2.sum())
        n_lost += int((~st2 & ~weak2).sum())
        n_fb = int((st2 & ~good).sum())
        idx = idx[good]
        if len(idx) and p.ncc_min > -1.0:
            similar = patch_ncc(A, p0[idx], B, p1[idx], p.ncc_half) >= p.ncc_min
            n_ncc = int((~similar).sum())
            idx = idx[similar]
        kept[idx] = True
    counts = FlowCounts(detected=n, lost=n_lost, min_eig=n_weak, outside=int(outside.sum()), fb=n_fb, ncc=n_ncc,
                        kept=int(kept.sum()))
    return PointFlow(q1, kept, counts)


# :func:`aligned` - the affine of the points' motion: fitted from at least this many points, on a grid of this step
ALIGN_MIN_POINTS = 8
ALIGN_STEP = 1e-6


def _fit_affine(a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """2x3 least-squares affine map of pixels ``a`` (N, 2) onto ``b``, once more without the pairs off it by over
    1 px and three times the median; None with too few pairs."""
    keep = np.ones(len(a), bool)
    A = None
    for _ in range(2):
        if keep.sum() < ALIGN_MIN_POINTS:
            return None
        X = np.column_stack([a[keep], np.ones(int(keep.sum()))])
        A = np.linalg.lstsq(X, b[keep], rcond=None)[0].T
        r = np.linalg.norm(a @ A[:, :2].T + A[:, 2] - b, axis=1)
        keep = r <= max(1.0, 3.0 * float(np.median(r[keep])))
    return A


def aligned(prev: np.ndarray, curr: np.ndarray, pts: np.ndarray, p: FlowParams, guess: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``prev`` warped onto ``curr`` by the affine that the points' motion fits, where ``pts`` lie in it, and where
    they land in ``curr`` (the start for :func:`track_points` from there; ``guess`` where a point was not found).
    The affine comes from one forward LK at half resolution (from ``guess``); without enough points, ``prev``,
    ``pts`` and ``guess`` as they are.

    Why: LK fits a translation to a window. When the scene comes closer the window's content grows about the point,
    and LK settles off it, towards the window's texture, by a few hundredths of a pixel a frame, the same way for
    the same point. Frame to frame those add up: on the simulator's 5.1 Hz loop, tracks were off their scene points
    by 0.3 px after 8-16 frames and 0.6 px after more, and that bent the trajectory (docs/results.md "Stop 53").
    Tracked from the warped image, the window's content has the size it has now, and the drift is 0.12 / 0.20 px."""
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    g = pts if guess is None else np.where(np.isfinite(guess), guess, pts).reshape(-1, 2)
    if len(pts) < ALIGN_MIN_POINTS:
        return prev, pts, guess
    small_prev, small_curr = cv2.pyrDown(prev), cv2.pyrDown(curr)
    lk = {'winSize': (p.lk_win, p.lk_win), 'maxLevel': max(p.lk_levels - 1, 0), 'criteria': _CRITERIA,
          'flags': cv2.OPTFLOW_USE_INITIAL_FLOW}
    p1, st, _ = cv2.calcOpticalFlowPyrLK(small_prev, small_curr, (pts / 2).astype(np.float32).reshape(-1, 1, 2),
                                         (g / 2).astype(np.float32).reshape(-1, 1, 2), **lk)
    found = 2.0 * p1.reshape(-1, 2).astype(np.float64)
    ok = st.ravel().astype(bool) & np.all(np.isfinite(found), axis=1)
    A = _fit_affine(pts[ok], found[ok])
    if A is None or not np.all(np.isfinite(A)):
        return prev, pts, guess
    A = np.round(A / ALIGN_STEP) * ALIGN_STEP       # the BLAS kernel's last bits must not move the warp's rounding
    h, w = prev.shape
    warped = cv2.warpAffine(prev, A, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return warped, pts @ A[:, :2].T + A[:, 2], np.where(ok[:, None], found, g)


def _patches(img: np.ndarray, pts: np.ndarray, half: int) -> np.ndarray:
    """(N, (2h+1)^2) bilinear samples of ``img`` around sub-pixel points, all in one cv2.remap."""
    off = np.arange(-half, half + 1, dtype=np.float32)
    gx, gy = np.tile(off, len(off)), np.repeat(off, len(off))
    xy = pts.reshape(-1, 2).astype(np.float32)
    return cv2.remap(img, xy[:, :1] + gx, xy[:, 1:] + gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def patch_ncc(img_a: np.ndarray, pts_a: np.ndarray, img_b: np.ndarray, pts_b: np.ndarray, half: int) -> np.ndarray:
    """Normalised cross-correlation (N,) of the (2h+1)^2 patches at ``pts_a`` in ``img_a`` and ``pts_b`` in
    ``img_b``; 0 where either patch is flat. Gain and offset invariant, so exposure changes do not count."""
    a = _patches(img_a, pts_a, half).astype(np.float64)
    b = _patches(img_b, pts_b, half).astype(np.float64)
    n = a.shape[1]
    sa, sb = a.sum(axis=1), b.sum(axis=1)
    va = np.einsum('ij,ij->i', a, a) - sa * sa / n
    vb = np.einsum('ij,ij->i', b, b) - sb * sb / n
    cab = np.einsum('ij,ij->i', a, b) - sa * sb / n
    den = np.sqrt(np.maximum(va, 0.0) * np.maximum(vb, 0.0))
    return np.where(den > 1e-6, cab / np.maximum(den, 1e-6), 0.0)


# :func:`register` - each track's birth patch aligned by an affine warp into every later image
REGISTER_HALF = 10          # the birth patch is (2h+1)^2 px, LK's window
REGISTER_ITERATIONS = 4     # inverse-compositional Gauss-Newton steps (from LK's position they converge in 2-4)
REGISTER_MAX_PX = 1.5       # a registration landing farther from the tracked pixel is a failure
REGISTER_MIN_NCC = 0.95     # ... and one correlating less with the birth patch: the track ends


@dataclass(frozen=True)
class BirthPatches:
    """What :func:`register` needs of each track's birth patch, computed once at its detection: the zero-mean patch
    (N, S*S) and its std (N,), and the inverse-compositional update matrix H^-1 SD^T (N, 6, S*S) of the affine warp
    (a11, a12, a21, a22, tx, ty) about the patch centre."""

    template: np.ndarray
    std: np.ndarray
    update: np.ndarray

    def take(self, idx: np.ndarray) -> BirthPatches:
        return BirthPatches(self.template[idx], self.std[idx], self.update[idx])

    @staticmethod
    def concat(parts: list[BirthPatches]) -> BirthPatches:
        return BirthPatches(*(np.concatenate([getattr(b, f.name) for b in parts]) for f in fields(BirthPatches)))

    @property
    def half(self) -> int:
        return (math.isqrt(self.template.shape[1]) - 1) // 2


def _grid(h: int) -> tuple[np.ndarray, np.ndarray]:
    """Patch pixel offsets from its centre (u right, v down), row-major as the patches are stored."""
    v, u = np.mgrid[-h:h + 1, -h:h + 1].astype(np.float64)
    return u.ravel(), v.ravel()


def _solve_spd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with a @ x = b for a stack of small symmetric positive definite ``a`` (N, k, k), ``b`` (N, k, m): Gauss-Jordan
    elimination written out, so that no LAPACK kernel (which rounds differently on each CPU) is involved. On the
    augmented rows [a | b], one whole-array update per column (the pivot row's own factor is zero)."""
    k = a.shape[1]
    m = np.concatenate([a.astype(np.float64), b.astype(np.float64)], axis=2)
    for j in range(k):
        m[:, j, :] /= m[:, j, j][:, None].copy()
        f = m[:, :, j].copy()
        f[:, j] = 0.0
        m -= f[:, :, None] * m[:, j, None, :]
    return m[:, :, k:]


def birth_patches(gray: np.ndarray, pts: np.ndarray, half: int = REGISTER_HALF) -> BirthPatches:
    """The birth patches ((2 ``half`` + 1)^2 px) of points detected at ``pts`` (N, 2) in ``gray``."""
    h = half
    size = 2 * h + 3                            # one more pixel each side for the central differences
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    big = np.empty((len(pts), size, size), np.float64)
    for i, (x, y) in enumerate(pts):
        big[i] = cv2.getRectSubPix(gray, (size, size), (float(x), float(y)), patchType=cv2.CV_32F)
    t = big[:, 1:-1, 1:-1].reshape(len(pts), -1)
    gx = 0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2]).reshape(len(pts), -1)
    gy = 0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1]).reshape(len(pts), -1)
    u, v = _grid(h)
    sd = np.stack([gx * u, gx * v, gy * u, gy * v, gx, gy], axis=1)        # (N, 6, S*S)
    hess = np.einsum('nip,njp->nij', sd, sd)
    hess += np.eye(6) * 1e-9 * np.maximum(np.trace(hess, axis1=1, axis2=2), 1.0)[:, None, None]
    update = _solve_spd(hess, sd)
    mean = t.mean(axis=1, keepdims=True)
    return BirthPatches(t - mean, (t - mean).std(axis=1), update)


def register(gray: np.ndarray, pts: np.ndarray, births: BirthPatches, linear: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each birth patch (``births``, affine ``linear`` (N, 2, 2) since its birth) lies in ``gray`` now, starting
    from ``pts`` (N, 2, the frame-to-frame LK positions): inverse-compositional Gauss-Newton over an affine warp
    (Baker-Matthews), every track at once, gain and offset normalised. Returns (positions, linear parts, ok); not ok
    (the input as it was) where the result lands over ``REGISTER_MAX_PX`` from ``pts``, correlates below
    ``REGISTER_MIN_NCC`` with the birth patch, or is not finite.

    Why: LK fits a translation of its window from one frame to the next. When the scene comes closer the window's
    content grows about the point and LK settles off it the same way every frame, so a track drifts from its scene
    point (0.20 px median after 16 frames on the simulator's loop even after :func:`aligned`). The birth patch
    registered with its scale and shear does not drift (0.06 px). And a track whose patch no longer fits any affine
    image of its birth patch is not on one static point (a corner made by two surfaces at different depths slides as
    they part): the front end ends it. On the papers' loop those few tracks (3-5 % of the observations off by over
    0.5 px) tilted the estimate by 0.3-0.5 deg on the first straight (docs/results.md "Stop 74")."""
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    n = len(pts)
    A = np.array(linear, np.float64).reshape(-1, 2, 2)
    if n == 0:
        return pts.copy(), A, np.zeros(0, bool)
    b = pts.copy()
    u, v = _grid(births.half)
    size = 2 * births.half + 1
    finite = np.all(np.isfinite(b), axis=1)
    b[~finite] = 0.0
    warped = np.zeros((n, size * size))
    for step in range(REGISTER_ITERATIONS + 1):
        mx = A[:, 0, :1] * u + A[:, 0, 1:] * v + b[:, :1]          # (N, S*S): where each patch pixel lands
        my = A[:, 1, :1] * u + A[:, 1, 1:] * v + b[:, 1:]
        warped = cv2.remap(gray, mx.reshape(-1, size).astype(np.float32), my.reshape(-1, size).astype(np.float32),
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(n, -1).astype(np.float64)
        if step == REGISTER_ITERATIONS:
            break
        w = warped - warped.mean(axis=1, keepdims=True)
        scale = births.std / np.maximum(w.std(axis=1), 1e-9)
        dp = np.einsum('nip,np->ni', births.update, w * scale[:, None] - births.template)
        D = np.eye(2) + dp[:, :4].reshape(-1, 2, 2)
        det = D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]
        det = np.where(np.abs(det) > 1e-9, det, 1.0)
        Dinv = np.stack([np.stack([D[:, 1, 1], -D[:, 0, 1]], -1), np.stack([-D[:, 1, 0], D[:, 0, 0]], -1)], 1)
        Dinv /= det[:, None, None]
        A = np.einsum('nij,njk->nik', A, Dinv)
        b = b - np.einsum('nij,nj->ni', A, dp[:, 4:])
    w = warped - warped.mean(axis=1, keepdims=True)
    den = np.sqrt(np.einsum('np,np->n', w, w) * np.einsum('np,np->n', births.template, births.template))
    ncc = np.einsum('np,np->n', w, births.template) / np.maximum(den, 1e-9)
    ok = finite & np.all(np.isfinite(b), axis=1) & np.all(np.isfinite(A), axis=(1, 2)) \
        & (np.linalg.norm(b - pts, axis=1) <= REGISTER_MAX_PX) & (ncc >= REGISTER_MIN_NCC)
    out = np.where(ok[:, None], b, pts)
    return out, np.where(ok[:, None, None], A, np.array(linear, np.float64).reshape(-1, 2, 2)), ok
