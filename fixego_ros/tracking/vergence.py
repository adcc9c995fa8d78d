"""Start-up vergence step (ROS-free): both cameras briefly fixate the same scene point, and its distance
follows from the known baseline. A metric scale aid, off by default.

Pieces:

* :func:`vergence_aims` - where to point the left head so the right fixation ray's epipolar curve (the
  ray's points between ``min_depth_m`` and ``max_depth_m`` seen by the left camera) lies in its image.
* :func:`find_partner_point` - the left pixel of the right camera's fixation point: NCC of the right's
  patch (warped by the rotation between the two cameras) along that curve, sub-pixel refinement (parabola
  along the curve, then ECC translation in 2-D), and an ambiguity check (margin to the second-best peak).
* :func:`triangulate_fixation` - the point on the right fixation ray closest to the left ray, its distance
  from the right camera centre (the rig origin), the first-order covariance from the rays' angular noise,
  and the vergence angle; nearly parallel rays are rejected.
* :class:`VergenceStep` - the left camera's state machine (wait for the right camera, aim, search, converge,
  triangulate, return), fed plain data by ``camera_node``; every phase is bounded in time.

Frames and kinematics as DESIGN.md §2 through :class:`~fixego_ros.geometry.rig.Rig`.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from fixego_ros.geometry.rig import Rig
from fixego_ros.tracking.servo import JointHistory, centring_angles


@dataclass
class VergenceParams:
    min_depth_m: float = 0.8         # epipolar search range along the right fixation ray
    max_depth_m: float = 10.0
    patch_half: int = 15             # NCC patch is (2h+1)^2 px
    ncc_min: float = 0.8             # best NCC below this: no match
    margin_min: float = 0.1          # best minus second-best NCC peak below this: ambiguous
    min_template_std: float = 4.0    # grey levels; a flatter right patch is textureless
    max_epipolar_px: float = 3.0     # refined match this far off the curve: rejected (calibration/mismatch)
    min_angle_deg: float = 0.5       # vergence angle below this: rays too parallel to triangulate
    pixel_sigma_px: float = 0.5      # fixation pixel noise (each camera)
    joint_sigma_deg: float = 0.033   # joint reading noise (EVI-D30: 1 unit = 0.114 deg, /sqrt(12))
    settle_px: float = 3.0           # both fixations this close to their principal points ...
    settle_frames: int = 3           # ... for this many consecutive frames
    timeout_s: float = 20.0          # the whole step (waiting, aiming, search, convergence)
    aim_tolerance_deg: float = 0.3   # the head counts as arrived within this of an aim
    aim_settle_s: float = 0.1        # and an image this long after arriving is searched
    aim_timeout_s: float = 4.0       # one aim (or the return) may take this long
    stamp_slop_s: float = 0.02       # right fixation matched to a left image stamp within this


# ------------------------------------------------------------------------------------------------ geometry
@dataclass(frozen=True)
class Triangulation:
    point_rig: np.ndarray     # on the right fixation ray, closest to the left ray (rig frame, m)
    distance_m: float         # |point_rig|: distance from the right camera centre
    std_m: float              # first-order std of distance_m
    angle_rad: float          # vergence angle between the two rays
    cov_rig: np.ndarray       # 3x3 first-order covariance of point_rig
    gap_m: float = 0.0        # closest distance between the rays
    ok: bool = True
    reason: str = ''


def _ray_point(r: np.ndarray, l: np.ndarray, c: np.ndarray) -> tuple[float, float, float]:
    """Parameters (s, t) of the closest points ``s r`` and ``c + t l`` of two rays, and their gap."""
    a, b, e = float(r @ r), float(r @ l), float(l @ l)
    d, f = float(r @ c), float(l @ c)
    den = a * e - b * b
    s = (d * e - b * f) / den
    t = (b * d - a * f) / den
    return s, t, float(np.linalg.norm(s * r - (c + t * l)))


def _perp_basis(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(v, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(v, e1)


def triangulate_fixation(ray_r: np.ndarray, ray_l: np.ndarray, c_l: np.ndarray, pixel_sigma_rad: float,
                         min_angle_rad: float = math.radians(0.5)) -> Triangulation:
    """Triangulate the right fixation point from the right ray (centre 0) and the left ray (centre ``c_l``),
    all in the rig frame. ``pixel_sigma_rad``: angular std of each ray (per axis, both rays). The point is
    taken on the right ray (it is the right camera's fixation point); the covariance is first order in the
    four ray angles. Nearly parallel rays, or a point behind a camera, give ``ok=False`` with a reason."""
    r = np.asarray(ray_r, float).reshape(3)
    r = r / np.linalg.norm(r)
    l = np.asarray(ray_l, float).reshape(3)
    l = l / np.linalg.norm(l)
    c = np.asarray(c_l, float).reshape(3)
    angle = float(np.arctan2(np.linalg.norm(np.cross(r, l)), float(r @ l)))
    nan3 = np.full(3, np.nan)
    if angle < min_angle_rad:
        return Triangulation(nan3, math.nan, math.nan, angle, np.full((3, 3), np.nan), math.nan, False,
                             f'rays nearly parallel (vergence {math.degrees(angle):.2f} deg < '
                             f'{math.degrees(min_angle_rad):.2f} deg)')
    s, t, gap = _ray_point(r, l, c)
    if s <= 0 or t <= 0:
        return Triangulation(nan3, math.nan, math.nan, angle, np.full((3, 3), np.nan), gap, False,
                             'rays meet behind a camera')
    point = s * r
    # first-order covariance: Jacobian of s*r over small rotations of each ray about two perpendicular axes
    J = np.zeros((3, 4))
    eps = 1e-7
    for k, (which, e) in enumerate([(0, v) for v in _perp_basis(r)] + [(1, v) for v in _perp_basis(l)]):
        out = []
        for sgn in (1.0, -1.0):
            rr = r + sgn * eps * e if which == 0 else r
            ll = l + sgn * eps * e if which == 1 else l
            ss, _, _ = _ray_point(rr, ll, c)
            out.append(ss * rr)
        J[:, k] = (out[0] - out[1]) / (2 * eps)
    cov = pixel_sigma_rad ** 2 * (J @ J.T)
    std = float(math.sqrt(max(float(r @ cov @ r), 0.0)))
    return Triangulation(point, float(s), std, angle, cov, gap)


# ------------------------------------------------------------------------------------------------ search
@dataclass(frozen=True)
class PartnerMatch:
    ok: bool
    reason: str                              # why it was rejected; '' when ok
    pixel: tuple[float, float] | None        # left pixel of the right fixation point (raw image)
    ncc: float = 0.0                         # NCC at the refined pixel
    margin: float = 0.0                      # best minus second-best NCC peak along the curve
    depth_m: float = math.nan                # depth along the right ray of the best curve sample (coarse)
    epipolar_px: float = math.nan            # distance of the refined pixel from the curve
    samples: int = 0                         # curve samples searched


def _right_ray(rig: Rig, pixel, joints) -> np.ndarray:
    return rig.pixels_to_rig_rays('right', np.asarray(pixel, float).reshape(1, 2), *joints)[0]


def epipolar_curve(rig: Rig, ray_r: np.ndarray, left_joints: tuple[float, float], min_depth_m: float,
                   max_depth_m: float, step_px: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Left pixels (N, 2) and depths (N,) of the right ray's points from ``min_depth_m`` to ``max_depth_m``
    (uniform in inverse depth, about ``step_px`` apart); points behind the left camera are left out."""
    C = rig.cam_to_rig('left', *left_joints)
    cam = rig.left

    def project(inv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = (np.asarray(ray_r, float)[None, :] / inv[:, None] - rig.c_L[None, :]) @ C
        front = d[:, 2] > 1e-6
        return cam.rays_to_pixels(d[front]), front

    lo, hi = 1.0 / max_depth_m, 1.0 / min_depth_m
    px, _ = project(np.linspace(hi, lo, 64))
    length = float(np.linalg.norm(np.diff(px, axis=0), axis=1).sum()) if len(px) > 1 else 0.0
    n = int(np.clip(math.ceil(length / step_px) + 1, 2, 20000))
    inv = np.linspace(hi, lo, n)
    px, front = project(inv)
    return px, 1.0 / inv[front]


def vergence_aims(rig: Rig, ray_r: np.ndarray, min_depth_m: float, max_depth_m: float,
                  margin_px: float = 20.0, max_aims: int = 6) -> list[tuple[float, float]]:
    """Left joint readings to visit so the epipolar curve of ``ray_r`` is covered: the inverse-depth range is
    split into as few pieces as let each piece's curve fit in the image (``margin_px`` from the border)
    when the head points at the piece's middle; nearest pieces first."""
    cam = rig.left
    lo, hi = 1.0 / max_depth_m, 1.0 / min_depth_m
    for k in range(1, max_aims + 1):
        edges = np.linspace(hi, lo, k + 1)
        aims, fits = [], True
        for a, b in itertools.pairwise(edges):
            mid = 0.5 * (a + b)
            q = rig.aim_readings('left', np.asarray(ray_r, float) / mid)
            px, depth = epipolar_curve(rig, ray_r, q, 1.0 / a, 1.0 / b, step_px=4.0)
            inside = (len(depth) > 0 and np.all(px[:, 0] >= margin_px) and np.all(px[:, 1] >= margin_px)
                      and np.all(px[:, 0] <= cam.width - 1 - margin_px)
                      and np.all(px[:, 1] <= cam.height - 1 - margin_px))
            fits = fits and bool(inside)
            aims.append(q)
        if fits or k == max_aims:
            return aims
    return []


def _rotation_jacobian(rig: Rig, right_pixel, right_joints, left_joints, at_left: np.ndarray) -> np.ndarray:
    """2x2 map of right-pixel offsets at ``right_pixel`` to left-pixel offsets (rotation only, infinite depth)."""
    Rr = rig.cam_to_rig('right', *right_joints)
    Rl = rig.cam_to_rig('left', *left_joints)
    p = np.asarray(right_pixel, float)
    pts = np.array([p, p + [1.0, 0.0], p + [0.0, 1.0]])
    rays = rig.right.pixels_to_rays(pts) @ Rr.T @ Rl          # in the left optical frame
    if np.any(rays[:, 2] <= 1e-6):
        return np.eye(2)
    q = rig.left.rays_to_pixels(rays)
    A = np.column_stack([q[1] - q[0], q[2] - q[0]])
    return A if np.all(np.isfinite(A)) and abs(np.linalg.det(A)) > 1e-3 else np.eye(2)


def _patches(gray: np.ndarray, centres: np.ndarray, h: int) -> np.ndarray:
    """(N, 2h+1, 2h+1) float32 bilinear patches centred on sub-pixel ``centres``."""
    g = np.arange(-h, h + 1, dtype=np.float32)
    n, s = len(centres), 2 * h + 1
    mx = (centres[:, 0].astype(np.float32)[:, None, None] + g[None, None, :]).repeat(s, axis=1)
    my = (centres[:, 1].astype(np.float32)[:, None, None] + g[None, :, None]).repeat(s, axis=2)
    out = cv2.remap(gray.astype(np.float32), mx.reshape(n * s, s), my.reshape(n * s, s), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(n, s, s)


def _ncc_many(template: np.ndarray, patches: np.ndarray) -> np.ndarray:
    t = template - template.mean()
    p = patches - patches.mean(axis=(1, 2), keepdims=True)
    den = np.sqrt(float((t * t).sum()) * (p * p).sum(axis=(1, 2)))
    return np.where(den > 1e-9, (p * t[None]).sum(axis=(1, 2)) / np.maximum(den, 1e-9), 0.0)


def find_partner_point(right_gray: np.ndarray, right_pixel: tuple[float, float],
                       right_joints: tuple[float, float], left_gray: np.ndarray,
                       left_joints: tuple[float, float], rig: Rig,
                       params: VergenceParams | None = None) -> PartnerMatch:
    """Left pixel of the scene point the right camera sees at ``right_pixel`` (joint *readings* of both
    heads at their image stamps). Searches the right ray's epipolar curve between ``params.min_depth_m`` and
    ``params.max_depth_m``; rejects (``ok=False``, ``reason``) a textureless patch, a best NCC below
    ``ncc_min``, an ambiguous match (second peak within ``margin_min``) or a curve outside the image."""
    p = params or VergenceParams()
    h = int(p.patch_half)
    rg = right_gray if right_gray.ndim == 2 else cv2.cvtColor(right_gray, cv2.COLOR_BGR2GRAY)
    lg = left_gray if left_gray.ndim == 2 else cv2.cvtColor(left_gray, cv2.COLOR_BGR2GRAY)
    ray_r = _right_ray(rig, right_pixel, right_joints)
    px, depth = epipolar_curve(rig, ray_r, left_joints, p.min_depth_m, p.max_depth_m)
    H, W = lg.shape
    m = h + 2
    inside = (px[:, 0] >= m) & (px[:, 1] >= m) & (px[:, 0] <= W - 1 - m) & (px[:, 1] <= H - 1 - m)
    px, depth = px[inside], depth[inside]
    if len(px) < 3:
        return PartnerMatch(False, 'epipolar curve outside the left image', None)
    # right patch resampled into the left camera's orientation (rotation-only homography, local affine)
    A = _rotation_jacobian(rig, right_pixel, right_joints, left_joints, px[len(px) // 2])
    Ai = np.linalg.inv(A)
    rp = np.asarray(right_pixel, float)
    M = np.column_stack([Ai, rp - Ai @ np.array([h, h], float)]).astype(np.float64)
    template = cv2.warpAffine(rg.astype(np.float32), M, (2 * h + 1, 2 * h + 1),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
    if float(template.std()) < p.min_template_std:
        return PartnerMatch(False, f'textureless right patch (std {template.std():.1f} grey levels)', None,
                            samples=len(px))
    scores = _ncc_many(template, _patches(lg, px, h))
    i = int(np.argmax(scores))
    best = float(scores[i])
    # second-best: the highest local maximum more than 3 px (along the curve) from the best
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(px, axis=0), axis=1))])
    peak = np.r_[False, (scores[1:-1] >= scores[:-2]) & (scores[1:-1] >= scores[2:]), False]
    peak[0], peak[-1] = scores[0] >= scores[1], scores[-1] >= scores[-2]
    far = np.abs(arc - arc[i]) > 3.0
    second = float(scores[peak & far].max()) if np.any(peak & far) else -1.0
    margin = best - second
    if best < p.ncc_min:
        return PartnerMatch(False, f'no match (best NCC {best:.2f} < {p.ncc_min:.2f})', None, best, margin,
                            float(depth[i]), samples=len(px))
    if margin < p.margin_min:
        return PartnerMatch(False, f'ambiguous match (NCC {best:.2f}, second peak {second:.2f})', None, best,
                            margin, float(depth[i]), samples=len(px))
    # sub-pixel: parabola along the curve, then ECC (NCC-maximising) translation in 2-D
    est = px[i].astype(float)
    if 0 < i < len(px) - 1:
        a, b, c = scores[i - 1], scores[i], scores[i + 1]
        den = a - 2 * b + c
        off = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if den < 0 else 0.0
        j = i + 1 if off > 0 else i - 1
        est = px[i] + abs(off) * (px[j] - px[i])
    refined = _ecc_refine(template, lg, est, h)
    if refined is not None and np.linalg.norm(refined - est) <= 2.0:
        est = refined
    ncc = float(_ncc_many(template, _patches(lg, est[None], h))[0])
    epi = float(np.min(np.linalg.norm(px - est[None], axis=1)))
    if epi > p.max_epipolar_px:
        return PartnerMatch(False, f'match {epi:.1f} px off the epipolar curve', None, ncc, margin,
                            float(depth[i]), epi, len(px))
    return PartnerMatch(True, '', (float(est[0]), float(est[1])), ncc, margin, float(depth[i]), epi, len(px))


def _ecc_refine(template: np.ndarray, gray: np.ndarray, est: np.ndarray, h: int, r: int = 4) -> np.ndarray | None:
    x0, y0 = round(float(est[0])) - h - r, round(float(est[1])) - h - r
    size = 2 * (h + r) + 1
    if x0 < 0 or y0 < 0 or x0 + size > gray.shape[1] or y0 + size > gray.shape[0]:
        return None
    roi = gray[y0:y0 + size, x0:x0 + size].astype(np.float32)
    warp = np.array([[1.0, 0.0, est[0] - h - x0], [0.0, 1.0, est[1] - h - y0]], np.float32)
    try:
        _, warp = cv2.findTransformECC(template.astype(np.float32), roi, warp, cv2.MOTION_TRANSLATION,
                                       (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4), None, 1)
    except cv2.error:
        return None
    out = np.array([x0 + h + warp[0, 2], y0 + h + warp[1, 2]], float)
    return out if np.all(np.isfinite(out)) else None


# ------------------------------------------------------------------------------------------------ step
@dataclass(frozen=True)
class Action:
    """What the camera node should do with the current left frame."""

    kind: str                                    # 'track' (as usual) | 'hold' (no tracking: head commanded)
    aim: tuple[float, float] | None = None       # 'hold': joint readings to drive the head to
    select: tuple[float, float] | None = None    # 'track': start a new fixation at this pixel first
    reselect: bool = False                       # 'track': select a new point as usual first (step over)


@dataclass
class VergenceResult:
    stamp: float
    point_rig: np.ndarray
    distance_m: float
    std_m: float
    angle_rad: float
    cov_rig: np.ndarray
    right_pixel: tuple[float, float]
    left_pixel: tuple[float, float]
    match: PartnerMatch
    duration_s: float


@dataclass
class _Frame:
    t: float
    pixel: tuple[float, float] | None
    fixation_id: int


class VergenceStep:
    """The left camera's start-up vergence, one attempt. Phases: ``waiting`` (for a settled right fixation
    with its image and joints), ``aiming`` (head driven to an aim from :func:`vergence_aims`, then the partner
    point is searched on an image taken after it arrived), ``centring`` (head driven straight at the match,
which is then found again near the centre), ``converging`` (the tracker holds the partner
    point, the usual servo centres it; triangulation once both fixations are settled), ``returning`` (head
    back to where it looked before), then ``done`` or ``failed``. The caller feeds the right camera's
    messages and each left frame, and calls :meth:`poll` (also from a timer, so timeouts fire without
    images). :attr:`result` is set once on success; :attr:`reason` on failure."""

    def __init__(self, rig: Rig, left_history: JointHistory, params: VergenceParams | None = None) -> None:
        self.rig, self.p = rig, params or VergenceParams()
        self.left_history = left_history
        self.right_history = JointHistory()
        self.right_images: deque[tuple[float, np.ndarray]] = deque(maxlen=8)
        self.right_fix: deque[tuple[float, tuple[float, float], int]] = deque(maxlen=120)
        self.left_frames: deque[_Frame] = deque(maxlen=120)
        self.phase = 'waiting'
        self.t_start: float | None = None
        self.t_phase = 0.0
        self.reason = ''
        self.result: VergenceResult | None = None
        self.match: PartnerMatch | None = None
        self.home: tuple[float, float] | None = None
        self._aims: list[tuple[float, float]] = []
        self._aim: tuple[float, float] | None = None
        self._arrived: float | None = None
        self._rejections: list[str] = []
        self._left_id: int | None = None
        self._right_id: int | None = None
        self._ended = ''            # 'done' | 'failed' once the measurement part is over
        self._note = ''             # what the converging phase is waiting for (for the timeout message)
        self.finished = False       # head back, independent fixation resumed

    # -------------------------------------------------------------------- inputs
    @property
    def wants_right_images(self) -> bool:
        return self.phase in ('waiting', 'aiming', 'centring')

    def add_right_image(self, t: float, gray: np.ndarray) -> None:
        if self.wants_right_images:
            self.right_images.append((t, gray))

    def add_right_fixation(self, t: float, pixel: tuple[float, float], fixation_id: int) -> None:
        self.right_fix.append((t, (float(pixel[0]), float(pixel[1])), int(fixation_id)))

    def add_right_joints(self, t: float, pan: float, tilt: float) -> None:
        self.right_history.add(t, pan, tilt)

    @property
    def status(self) -> str:
        """'running: <phase>' | 'done' | 'failed: <reason>' (for diagnostics)."""
        if self._ended == 'done':
            return 'done'
        if self._ended == 'failed':
            return f'failed: {self.reason}'
        return f'running: {self.phase}'

    # -------------------------------------------------------------------- helpers
    def _centred(self, side: str, pixel) -> bool:
        cam = self.rig.camera(side)
        return math.hypot(pixel[0] - cam.cx, pixel[1] - cam.cy) <= self.p.settle_px

    def _right_fix_near(self, t: float) -> tuple[float, tuple[float, float], int] | None:
        best = None
        for f in self.right_fix:
            if abs(f[0] - t) <= self.p.stamp_slop_s and (best is None or abs(f[0] - t) < abs(best[0] - t)):
                best = f
        return best

    def _right_triple(self):
        """Newest right (stamp, image, fixation pixel, fixation id, joints) with a centred fixation."""
        fixes = {round(f[0], 6): f for f in self.right_fix}
        for t, img in reversed(self.right_images):
            f = fixes.get(round(t, 6))
            if f is None or not self._centred('right', f[1]):
                continue
            q = self.right_history.at(t, max_extrapolation_s=0.0)
            if q is not None:
                return t, img, f[1], f[2], q
        return None

    def _fail(self, now: float, reason: str) -> None:
        self.reason, self._ended = reason, 'failed'
        self._start_return(now)

    def _start_return(self, now: float) -> None:
        self.right_images.clear()
        if self.home is None:
            self.phase, self.finished = 'ended', True
            return
        self.phase, self.t_phase, self._aim, self._arrived = 'returning', now, self.home, None

    def _reached(self, now: float, aim: tuple[float, float]) -> bool:
        latest = self.left_history.latest()
        tol = math.radians(self.p.aim_tolerance_deg)
        if latest is None or abs(latest[1] - aim[0]) > tol or abs(latest[2] - aim[1]) > tol:
            self._arrived = None
            return False
        if self._arrived is None:
            self._arrived = latest[0]
        return True

    def _next_aim(self, now: float) -> None:
        if not self._aims:
            why = '; '.join(self._rejections) or 'no aim covers the search range'
            self._fail(now, f'partner point not found ({why})')
            return
        self._aim = self._aims.pop(0)
        self._arrived = None
        self.t_phase = now

    # -------------------------------------------------------------------- the left camera's frames
    def _action(self) -> Action:
        if self.phase in ('aiming', 'centring', 'returning') and self._aim is not None:
            return Action('hold', aim=self._aim)
        return Action('track')

    def on_left_image(self, t: float, gray: np.ndarray, now: float) -> Action:
        """Call for each left image (before tracking). ``now``: the node's clock (same time base as stamps)."""
        if self.t_start is None:
            self.t_start = now
        self.poll(now)
        if self.phase == 'waiting':
            trip = self._right_triple()
            home = self.left_history.latest()
            if trip is None or home is None:
                return Action('track')
            _, _, rpx, rid, rq = trip
            self.home = (home[1], home[2])
            self._right_id = rid
            self._aims = vergence_aims(self.rig, _right_ray(self.rig, rpx, rq), self.p.min_depth_m,
                                       self.p.max_depth_m, margin_px=self.p.patch_half + 4)
            self.phase = 'aiming'
            self._next_aim(now)
            return self._action()
        if self.phase in ('aiming', 'centring'):
            # search on an image taken after the head arrived; a match found from an aim is first centred
            # by a direct head move (too fast for the tracker), then found again near the centre
            assert self._aim is not None
            if not self._reached(now, self._aim) or t < self._arrived + self.p.aim_settle_s:
                if now - self.t_phase > self.p.aim_timeout_s:
                    if self.phase == 'centring':
                        self._fail(now, 'the head did not reach the partner point')
                    else:
                        self._rejections.append('head did not reach an aim')
                        self._next_aim(now)
                return self._action()
            lq = self.left_history.at(t, max_extrapolation_s=0.1)
            trip = self._right_triple()
            if lq is None or trip is None:
                return self._action()
            _, rimg, rpx, rid, rq = trip
            if rid != self._right_id:
                self._fail(now, 'the right camera re-selected its fixation point')
                return self._action()
            m = find_partner_point(rimg, rpx, rq, gray, lq, self.rig, self.p)
            self.match = m
            if not m.ok:
                if self.phase == 'centring':
                    self._fail(now, f'partner point not found again after centring it ({m.reason})')
                else:
                    self._rejections.append(m.reason)
                    self._next_aim(now)
                return self._action()
            if self.phase == 'aiming' and not self._centred('left', m.pixel):
                self.phase, self.t_phase, self._arrived = 'centring', now, None
                self._aim = centring_angles(self.rig.left, m.pixel, *lq, self.rig.pan_tilt_left)
                return self._action()
            self.phase, self.t_phase = 'converging', now
            self.right_images.clear()
            return Action('track', select=m.pixel)
        if self.phase == 'returning':
            assert self._aim is not None
            if (self._reached(now, self._aim) and t >= self._arrived + self.p.aim_settle_s) \
                    or now - self.t_phase > self.p.aim_timeout_s:
                self.phase, self.finished = 'ended', True
                return Action('track', reselect=True)
            return self._action()
        return Action('track')

    def on_left_fixation(self, t: float, pixel: tuple[float, float] | None, fixation_id: int,
                         reselected: bool) -> None:
        """Call after tracking each left frame (also in other phases: it is ignored there)."""
        if self.phase != 'converging':
            return
        if self._left_id is None and reselected:
            self._left_id = fixation_id
        self.left_frames.append(_Frame(t, pixel, fixation_id))

    def poll(self, now: float) -> VergenceResult | None:
        """Timeouts, and the triangulation once both fixations have settled. Returns the result once."""
        if self._ended or self.t_start is None:
            return None
        if now - self.t_start > self.p.timeout_s:
            note = f' ({self._note})' if self._note else ''
            self._fail(now, f'timeout after {self.p.timeout_s:.0f} s in phase {self.phase}{note}')
            return None
        if self.phase != 'converging':
            return None
        frames = list(self.left_frames)
        if frames and (frames[-1].pixel is None or frames[-1].fixation_id != self._left_id):
            self._fail(now, 'the left camera lost the partner point')
            return None
        if any(f[2] != self._right_id for f in self.right_fix if frames and f[0] >= frames[0].t):
            self._fail(now, 'the right camera re-selected its fixation point')
            return None
        # the newest settle_frames left frames that have a right fixation and both joint states, all centred
        # (frames still lacking a partner message, or whose joint state was dropped, are skipped)
        run: list[tuple[_Frame, tuple]] = []
        for f in reversed(frames[-60:]):
            if f.pixel is None:
                break
            rf = self._right_fix_near(f.t)
            lq = self.left_history.at(f.t, max_extrapolation_s=0.0)
            rq = self.right_history.at(rf[0], max_extrapolation_s=0.0) if rf is not None else None
            if rf is None or lq is None or rq is None:
                continue
            if not (self._centred('left', f.pixel) and self._centred('right', rf[1])):
                lc, rc = self.rig.left.center, self.rig.right.center
                self._note = (f'fixations {math.dist(f.pixel, lc):.1f} px (left) and {math.dist(rf[1], rc):.1f} px '
                              f'(right) from the principal points')
                break
            run.append((f, (rf, lq, rq)))
            if len(run) >= self.p.settle_frames:
                break
        if len(run) < self.p.settle_frames:
            if not run and not self._note:
                self._note = 'no left frame matched with a right fixation and both joint states'
            return None
        f, (rf, lq, rq) = run[0]
        sigma = math.hypot(self.p.pixel_sigma_px / self.rig.left.fx, math.radians(self.p.joint_sigma_deg))
        ray_r = _right_ray(self.rig, rf[1], rq)
        ray_l = self.rig.pixels_to_rig_rays('left', np.asarray(f.pixel, float).reshape(1, 2), *lq)[0]
        tri = triangulate_fixation(ray_r, ray_l, self.rig.c_L, sigma, math.radians(self.p.min_angle_deg))
        if not tri.ok:
            self._fail(now, tri.reason)
            return None
        self.result = VergenceResult(f.t, tri.point_rig, tri.distance_m, tri.std_m, tri.angle_rad, tri.cov_rig,
                                     rf[1], f.pixel, self.match, now - self.t_start)
        self._ended = 'done'
        self._start_return(now)
        return self.result
