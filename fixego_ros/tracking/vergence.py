"""Vergence steps (ROS-free): both cameras briefly fixate the same scene point, and its distance follows from
the known baseline. The rig's own metric scale aid, repeated while it runs.

Pieces:

* :func:`vergence_aim_depths` - where along the right fixation ray to point the left head so the ray's
  epipolar curve (its points between ``min_depth_m`` and ``max_depth_m`` seen by the left camera) lies in its
  image.
* :func:`find_partner_point` - the left pixel of the right camera's fixation point: NCC of the right's
  patch (warped by the rotation between the two cameras) along that curve, sub-pixel refinement (parabola
  along the curve, then ECC translation in 2-D), and an ambiguity check (margin to the second-best peak).
* :func:`triangulate_fixation` - the point on the right fixation ray closest to the left ray, its distance
  from the right camera centre (the rig origin), the first-order covariance from the rays' angular noise,
  and the vergence angle; nearly parallel rays are rejected.
* :func:`average_samples` - one measurement from several frames while both heads hold the point: one frame's
  quantised joint readings give ~1 % at 3 m; the rig moves, so the readings change and averaging helps.
* :class:`VergenceStep` - the left camera's state machine for one step (wait for the right camera, aim, search,
  converge, average, return), fed plain data by ``camera_node``; every phase is bounded in time.
* :class:`VergenceScheduler` - when to run a step (start-up, a new right fixation point, a request, a period,
  a retry after a failure; a minimum interval between steps).

Frames and kinematics as DESIGN.md §2 through :class:`~fixego_ros.geometry.rig.Rig`.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from fixego_ros.geometry.rig import Rig
from fixego_ros.tracking.servo import JointHistory


@dataclass
class VergenceParams:
    min_depth_m: float = 0.8         # epipolar search range along the right fixation ray
    max_depth_m: float = 10.0
    prior_depth_m: float | None = None  # first aim where the right ray is this far (e.g. the last measurement)
    patch_half: int = 15             # NCC patch is (2h+1)^2 px
    ncc_min: float = 0.8             # best NCC below this: no match
    match_ncc_min: float = 0.95      # the refined match's NCC below this: not the same point closely enough
    margin_min: float = 0.1          # best minus second-best NCC peak below this: ambiguous
    min_template_std: float = 4.0    # grey levels; a flatter right patch is textureless
    max_epipolar_px: float = 3.0     # refined match this far off the curve: rejected (calibration/mismatch)
    min_angle_deg: float = 0.5       # vergence angle below this: rays too parallel to triangulate
    pixel_sigma_px: float = 0.3      # fixation pixel noise (each camera; one correspondence per step)
    joint_sigma_deg: float = 0.033   # joint reading noise (EVI-D30: 1 unit = 0.114 deg, /sqrt(12))
    timing_sigma_s: float = 0.005    # time uncertainty of a reading at an image stamp (x head speed: its error)
    timing_bias_s: float = 0.001     # ... the part common to a step's frames, which averaging does not reduce
    select_px: float = 60.0          # a match this close to the centre is fixated directly (no centring move)
    max_interruption_s: float = 1.8  # bound on a step's head moves (out, search, back; predicted): a longer one is
                                     # refused, an extra move that would exceed it is not made (the head returns)
    settle_px: float = 60.0          # both fixations this close to their principal points ...
    max_rate_deg_s: float = 60.0     # ... and both heads turning at most this fast (a fast head's reading is off)
    motion_window_s: float = 0.05    # head speed at a stamp: from its readings this long before and after
    settle_frames: int = 3           # ... for this many consecutive frames, then
    frames: int = 20                 # this many settled frames are averaged into one measurement
    hold_timeout_s: float = 1.0      # bound on settling, and on gathering (then what is there, >= settle_frames)
    max_scatter: float = 5.0         # frames scattering more than this many stds about their fit: rejected
    max_rel_std: float = 0.05        # a measurement less sure than this share of its distance: rejected
    wait_timeout_s: float = 10.0     # waiting for a settled right fixation (the left keeps its own point)
    timeout_s: float = 5.0           # from leaving the own point to the measurement (then the head returns)
    aim_tolerance_deg: float = 0.3   # the head counts as arrived within this of an aim
    aim_settle_s: float = 0.04       # and an image this long after arriving is searched
    aim_timeout_s: float = 3.0       # one head move (aim, centring, return) may take this long (EVI-D30: 200 deg
                                     # at 80 deg/s is 2.5 s)
    slew_deg_s: tuple[float, float] = (80.0, 50.0)  # the left head's fastest pan, tilt: a move's duration
    move_latency_s: float = 0.12     # a move's duration beyond turn / slew (command and ACK, the readings that
                                     # tell the head arrived, aim_settle_s, the image searched)
    lead_window_s: float = 0.2       # the right head's rate (the lead of an aim on a turning rig) over this long
    plan_angle_deg: float = 1.0      # no step when the right point's vergence is less (on an arc it only shrinks)
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
    jacobian: np.ndarray | None = None   # 3x4: point_rig over two small rotations of the right ray, then the left


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


def ray_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) between two rays: atan2 of |a x b| and a . b, exact also for nearly parallel rays."""
    return math.atan2(float(np.linalg.norm(np.cross(a, b))), float(a @ b))


def triangulate_fixation(ray_r: np.ndarray, ray_l: np.ndarray, c_l: np.ndarray,
                         pixel_sigma_rad: float | tuple[float, float],
                         min_angle_rad: float = math.radians(0.5)) -> Triangulation:
    """Triangulate the right fixation point from the right ray (centre 0) and the left ray (centre ``c_l``),
    all in the rig frame. ``pixel_sigma_rad``: angular std of each ray per axis (one for both, or right, left).
    The point is taken on the right ray (it is the right camera's fixation point); the covariance is first
    order in the four ray angles. Nearly parallel rays, or a point behind a camera, give ``ok=False`` with a
    reason."""
    sig_r, sig_l = (pixel_sigma_rad, pixel_sigma_rad) if np.isscalar(pixel_sigma_rad) else pixel_sigma_rad
    r = np.asarray(ray_r, float).reshape(3)
    r = r / np.linalg.norm(r)
    l = np.asarray(ray_l, float).reshape(3)
    l = l / np.linalg.norm(l)
    c = np.asarray(c_l, float).reshape(3)
    angle = ray_angle(r, l)
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
    cov = sig_r ** 2 * (J[:, :2] @ J[:, :2].T) + sig_l ** 2 * (J[:, 2:] @ J[:, 2:].T)
    std = float(math.sqrt(max(float(r @ cov @ r), 0.0)))
    return Triangulation(point, float(s), std, angle, cov, gap, jacobian=J)


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


def vergence_aim_depths(rig: Rig, ray_r: np.ndarray, min_depth_m: float, max_depth_m: float,
                        margin_px: float = 20.0, max_aims: int = 6) -> list[float]:
    """Depths along ``ray_r`` to point the left head at so the ray's epipolar curve is covered: the inverse-depth
    range is split into as few pieces as let each piece's curve fit in the image (``margin_px`` from the border)
    when the head points at the piece's middle; nearest pieces first."""
    cam = rig.left
    lo, hi = 1.0 / max_depth_m, 1.0 / min_depth_m
    for k in range(1, max_aims + 1):
        edges = np.linspace(hi, lo, k + 1)
        depths, fits = [], True
        for a, b in itertools.pairwise(edges):
            mid = 0.5 * (a + b)
            q = rig.aim_readings('left', np.asarray(ray_r, float) / mid)
            px, depth = epipolar_curve(rig, ray_r, q, 1.0 / a, 1.0 / b, step_px=4.0)
            inside = (len(depth) > 0 and np.all(px[:, 0] >= margin_px) and np.all(px[:, 1] >= margin_px)
                      and np.all(px[:, 0] <= cam.width - 1 - margin_px)
                      and np.all(px[:, 1] <= cam.height - 1 - margin_px))
            fits = fits and bool(inside)
            depths.append(1.0 / mid)
        if fits or k == max_aims:
            return depths
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
    ``ncc_min``, an ambiguous match (second peak within ``margin_min``), a curve outside the image, or a refined
    match whose NCC stays below ``match_ncc_min``. That last bound is on the measurement's accuracy, not on finding
    the point: of 603 live steps (docs/results.md "Stop 79"), those whose match correlated below 0.95 were more than
    1 % off in 24 of 32 (median 3.0 %, up to 13 %), the others in 98 of 571 (median 0.4 %)."""
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
    if ncc < p.match_ncc_min:
        return PartnerMatch(False, f'the match correlates too weakly to measure (NCC {ncc:.2f} < '
                                   f'{p.match_ncc_min:.2f})', None, ncc, margin, float(depth[i]), epi, len(px))
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


# ------------------------------------------------------------------------------------------------ averaging
@dataclass(frozen=True)
class VergenceSample:
    """One frame with both fixations settled on the point: the two rig-frame rays at one image stamp, and how
    fast each head turned around it (a moving head's reading is quantised and its time uncertain)."""

    t: float
    ray_r: np.ndarray                            # right fixation ray (rig frame at t)
    ray_l: np.ndarray                            # left fixation ray (rig frame at t)
    readings: tuple[float, float, float, float]  # left pan, tilt, right pan, tilt (rad) at t
    right_pixel: tuple[float, float]
    left_pixel: tuple[float, float]
    rates: tuple[float, float] = (0.0, 0.0)      # angular speed of the right, left head around t (rad/s)
    moving: tuple[bool, bool] = (True, True)     # False: the head's readings did not change around t (exact)


@dataclass(frozen=True)
class AveragedFixation:
    """The right fixation point from several frames (see :func:`average_samples`)."""

    ok: bool
    reason: str
    t: float = math.nan                  # stamp of the reference frame (nearest the frames' weighted mean time)
    point_rig: np.ndarray | None = None  # on the right ray of that frame, at the fitted distance
    distance_m: float = math.nan
    std_m: float = math.nan              # std of distance_m (see average_samples)
    cov_rig: np.ndarray | None = None
    angle_rad: float = math.nan          # vergence angle of the reference frame
    frames: int = 0
    distinct_readings: int = 0           # frames whose joint readings differ from every other frame's
    scatter_m: float = math.nan          # RMS of the distances about the fitted line
    rate_mps: float = 0.0                # fitted rate of change of the distance (the rig moves)
    right_pixel: tuple[float, float] | None = None
    left_pixel: tuple[float, float] | None = None


def _joint_sigma(joint_sigma_rad: float, timing_sigma_s: float, rate: float, moving: bool) -> float:
    """Angular std of one head's reading at an image stamp: its quantisation while it moves (a head at rest reads
    exactly where it stands), and the reading's time uncertainty times its speed."""
    return math.hypot(joint_sigma_rad if moving else 0.0, rate * timing_sigma_s)


def average_samples(samples: list[VergenceSample], c_l: np.ndarray, pixel_sigma_rad: float, joint_sigma_rad: float,
                    min_angle_rad: float = math.radians(0.5), max_scatter: float = 5.0,
                    timing_sigma_s: float = 0.005, timing_bias_s: float = 0.0,
                    max_rel_std: float = math.inf) -> AveragedFixation:
    """Combine frames into one measurement of the right fixation point. The rig may move meanwhile, so the
    distance is fitted as a line in time (each frame weighted by its first-order variance) and read at the
    frame nearest the weighted mean time; the point is that distance along that frame's right ray.

    Variance of the fitted distance, honestly: the pixel part is one correspondence, found once and then tracked,
    so averaging does not reduce it; the joint-reading part (quantisation, and reading time x head speed) is
    independent only between frames whose readings differ (a head at rest repeats its reading); and that part
    is never taken below what the frames' own scatter about the line says. A reading-time error common to the
    frames (``timing_bias_s``, times each head's rate) does not average either: on the demo's arcs (heads at
    20-30 deg/s) the left head's readings lagged 0.2-1.8 ms over a step, and steps there were 1-5 % off with a
    stated std that had averaged it away. Frames scattering more than
    ``max_scatter`` times their first-order std (a partner point lost or slipped) are rejected, and so is a
    measurement whose std exceeds ``max_rel_std`` of its distance: there the geometry (a point seen near the
    baseline's direction, or far) magnifies the rays' errors beyond the first order, and the std understates them.
    Of 316 demo steps (stop 85), the 18 above 5 % held all five that were over 10 % off (21-72 %, at 6-35 stated
    stds); the 298 kept were at most 8.6 % off."""
    if not samples:
        return AveragedFixation(False, 'no frame with both fixations settled')
    tris = [triangulate_fixation(s.ray_r, s.ray_l, c_l, 1.0, min_angle_rad) for s in samples]
    bad = next((tri for tri in tris if not tri.ok), None)
    if bad is not None:
        return AveragedFixation(False, bad.reason, frames=len(samples))
    n = len(samples)
    t = np.array([s.t for s in samples])
    d = np.array([tri.distance_m for tri in tris])
    sig_j = np.array([[_joint_sigma(joint_sigma_rad, timing_sigma_s, s.rates[k], s.moving[k]) for k in (0, 1)]
                      for s in samples])
    a = np.zeros((n, 2))            # variance of the distance per unit angular variance of the right, left ray
    for i, tri in enumerate(tris):
        u = tri.point_rig / np.linalg.norm(tri.point_rig)
        g = u @ tri.jacobian
        a[i] = g[:2] @ g[:2], g[2:] @ g[2:]
    v_pix = pixel_sigma_rad ** 2 * a.sum(axis=1)
    v_joint = (sig_j ** 2 * a).sum(axis=1)
    w = 1.0 / np.maximum(v_pix + v_joint, 1e-18)
    ref = int(np.argmin(np.abs(t - float(w @ t) / float(w.sum()))))
    k = 2 if n >= 3 and float(np.ptp(t)) > 1e-6 else 1
    X = np.column_stack([np.ones(n), t - t[ref]])[:, :k]
    Ainv = np.linalg.inv(X.T @ (w[:, None] * X))
    c = (Ainv @ (X.T * w))[0]                       # the fitted distance is sum(c * d)
    coef = Ainv @ (X.T @ (w * d))
    resid = d - X @ coef
    distinct = len({tuple(round(x, 9) for x in s.readings) for s in samples})
    var_pix = float(np.abs(c) @ np.sqrt(v_pix)) ** 2
    var_joint = float((c * c) @ v_joint) * n / distinct
    var_scatter = 0.0
    if n > k:
        chi2_dof = float(w @ (resid * resid)) / (n - k)
        if math.sqrt(chi2_dof) > max_scatter:
            return AveragedFixation(False, f'the frames disagree (distances scatter {math.sqrt(chi2_dof):.1f} times '
                                           f'their std)', frames=n)
        var_scatter = chi2_dof * float((c * c) @ (v_pix + v_joint))
    v_bias = timing_bias_s ** 2 * (a * np.array([s.rates for s in samples]) ** 2).sum(axis=1)
    var_bias = float(np.abs(c) @ np.sqrt(v_bias)) ** 2
    var = var_pix + var_bias + max(var_joint, var_scatter)
    s_ref = samples[ref]
    tri = triangulate_fixation(s_ref.ray_r, s_ref.ray_l, c_l,
                               (math.hypot(pixel_sigma_rad, sig_j[ref, 0]), math.hypot(pixel_sigma_rad, sig_j[ref, 1])),
                               min_angle_rad)
    u = tri.point_rig / np.linalg.norm(tri.point_rig)
    P = np.eye(3) - np.outer(u, u)
    cov = P @ tri.cov_rig @ P + var * np.outer(u, u)
    dist = float(coef[0])
    if math.sqrt(var) > max_rel_std * dist:
        return AveragedFixation(False, f'too weak to measure the distance (std {100 * math.sqrt(var) / dist:.1f} % of '
                                       f'{dist:.2f} m > {100 * max_rel_std:.1f} %; vergence '
                                       f'{math.degrees(tri.angle_rad):.2f} deg)', frames=n)
    return AveragedFixation(True, '', float(t[ref]), dist * u, dist, math.sqrt(var), cov, tri.angle_rad, n, distinct,
                            float(np.sqrt(np.mean(resid * resid))), float(coef[1]) if k == 2 else 0.0,
                            s_ref.right_pixel, s_ref.left_pixel)


# ------------------------------------------------------------------------------------------------ step
@dataclass(frozen=True)
class Action:
    """What the camera node should do with the current left frame."""

    kind: str                                    # 'track' (as usual) | 'hold' (no tracking: head commanded)
    aim: tuple[float, float] | None = None       # 'hold': joint readings to drive the head to
    select: tuple[float, float] | None = None    # 'track': start a new fixation at this pixel first
    rate: tuple[float, float] = (0.0, 0.0)       # with select: how fast its centring angles drift (rad/s)
    reselect: bool = False                       # 'track': select a new point as usual first (step over)


@dataclass
class VergenceResult:
    stamp: float                  # the reference left image's stamp
    point_rig: np.ndarray
    distance_m: float
    std_m: float
    angle_rad: float
    cov_rig: np.ndarray
    right_pixel: tuple[float, float]
    left_pixel: tuple[float, float]
    match: PartnerMatch
    duration_s: float             # from the step's start (including the wait for the right camera)
    frames: int = 1
    distinct_readings: int = 1
    scatter_m: float = 0.0
    rate_mps: float = 0.0


@dataclass
class _Frame:
    t: float
    pixel: tuple[float, float] | None
    fixation_id: int


class VergenceStep:
    """One vergence step of the left camera. Phases: ``waiting`` (until both fixations have settled - near their
    principal points, both heads turning slowly - and the right one has its image and joints; the left keeps its
    own point meanwhile), ``aiming`` (head driven to an aim - first where the
    right ray is at ``prior_depth_m``, then those of :func:`vergence_aim_depths` - and the partner point searched on an
    image taken after it arrived), ``centring`` (only for a match far from the centre: head driven straight at
    it, which is then found again), ``converging`` (the tracker holds the partner point, the usual servo centres
    it; once both fixations have settled, ``frames`` frames are averaged by :func:`average_samples` - or fewer, at
    least ``settle_frames``, if the right re-selects or the left loses the point first), ``returning`` (head back
    to where it looked before; cut short, the own point selected where the head is, when the right camera has no
    fixation: never both cameras without one), then ``ended`` with :attr:`result` or :attr:`reason`. A point beyond
    the left head's range, or whose moves there and back would take longer than ``max_interruption_s`` (predicted
    from the head's top speeds, :meth:`_move_s`), fails before the head moves; a further aim or a centring move that
    would take the step past that bound is not made (the head returns).

    The caller feeds the right camera's messages and each left frame, and calls :meth:`poll` (also from a timer,
    so timeouts fire without images). Bounds: ``wait_timeout_s`` on waiting, ``timeout_s`` from leaving the own
    point to the measurement, ``aim_timeout_s`` on each head move (the return included), ``hold_timeout_s`` on
    gathering frames. :attr:`interrupted_s` is the time the left published no valid fixation (head driven by the
    step), :attr:`away_s` the time from leaving its own point to selecting a new one."""

    def __init__(self, rig: Rig, left_history: JointHistory, params: VergenceParams | None = None,
                 right_history: JointHistory | None = None,
                 left_range: tuple[tuple[float, float], tuple[float, float]] | None = None,
                 left_joints: Callable[[float], tuple[float, float] | None] | None = None) -> None:
        self.rig, self.p = rig, params or VergenceParams()
        self.left_range = left_range   # ((pan min, max), (tilt min, max)) readings the left head can reach
        self.left_history = left_history
        # the left head's angles at a frame's stamp for the measurement, once readings after it exist; the caller's
        # best (the servo's commanded motion replayed between readings), else a straight line between readings
        self.left_joints = left_joints or (lambda t: self.left_history.at(t, max_extrapolation_s=0.0))
        self.right_history = right_history if right_history is not None else JointHistory()
        self.right_images: deque[tuple[float, np.ndarray]] = deque(maxlen=8)
        self.right_fix: deque[tuple[float, tuple[float, float], int]] = deque(maxlen=120)
        self.left_frames: deque[_Frame] = deque(maxlen=120)
        self._own: deque[tuple[tuple[float, float] | None, int]] = deque(maxlen=8)   # left's own point (waiting)
        self._sample_cache: dict[float, VergenceSample | str] = {}
        self.phase = 'waiting'
        self._waiting_for = ''          # why it is still waiting (diagnostics, and the timeout's message)
        self.t_start: float | None = None
        self.t_phase = 0.0
        self.reason = ''
        self.result: VergenceResult | None = None
        self.match: PartnerMatch | None = None
        self.home: tuple[float, float] | None = None
        self._aims: list[np.ndarray] = []     # rig-frame points to aim at, as seen at _t_plan
        self._t_plan = 0.0
        self._aim: tuple[float, float] | None = None
        self._arrived: float | None = None
        self._rejections: list[str] = []
        self._left_id: int | None = None
        self._right_id: int | None = None
        self._ended = ''            # 'done' | 'failed' once the measurement part is over
        self._note = ''             # what the converging phase is waiting for (for the timeout message)
        self._t_settled: float | None = None
        self.t_left: float | None = None      # left its own point (first head move)
        self.t_fixating: float | None = None  # fixates the partner point (valid fixation published again)
        self.t_return: float | None = None    # head driven back
        self.t_back: float | None = None      # own point selected again
        self.finished = False       # head back, independent fixation resumed
        self.needs_reselect = False  # finished by poll: the caller must select the left's own point again
        self.timeline: list[tuple[str, float]] = []   # (phase or event, node time): where a step spends its time

    # -------------------------------------------------------------------- inputs
    @property
    def wants_right_images(self) -> bool:
        return self.phase in ('waiting', 'aiming', 'centring')

    def add_right_image(self, t: float, gray: np.ndarray) -> None:
        if self.wants_right_images:
            self.right_images.append((t, gray))

    def add_right_fixation(self, t: float, pixel: tuple[float, float], fixation_id: int) -> None:
        """A right fixation pixel; a negative id (the right camera's "no valid fixation") is no pixel: ignored,
        else it would read as the right camera re-selecting its point."""
        if fixation_id < 0:
            return
        self.right_fix.append((t, (float(pixel[0]), float(pixel[1])), int(fixation_id)))

    def add_right_joints(self, t: float, pan: float, tilt: float) -> None:
        self.right_history.add(t, pan, tilt)

    @property
    def status(self) -> str:
        """'running: <phase>' | 'running: returning (measured | failed: <reason>)' | 'done' | 'failed: <reason>'
        (for diagnostics)."""
        outcome = 'done' if self._ended == 'done' else f'failed: {self.reason}' if self._ended else ''
        if not outcome:
            return f'running: {self.phase}' + (f' ({self._waiting_for})' if self.phase == 'waiting'
                                               and self._waiting_for else '')
        if not self.finished:
            return f'running: {self.phase} ({"measured" if self._ended == "done" else outcome})'
        return outcome

    @property
    def succeeded(self) -> bool:
        return self._ended == 'done'

    @property
    def interrupted_s(self) -> float:
        """Time the left camera published no valid fixation because the step drove its head (so far)."""
        if self.t_left is None:
            return 0.0
        end = self.t_back if self.t_back is not None else self.t_phase
        if self.t_fixating is None:
            return end - self.t_left
        return (self.t_fixating - self.t_left) + (end - self.t_return if self.t_return is not None else 0.0)

    @property
    def away_s(self) -> float:
        """Time from leaving the left's own point to selecting a new one (0 when it never left)."""
        if self.t_left is None:
            return 0.0
        return (self.t_back if self.t_back is not None else self.t_phase) - self.t_left

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

    @staticmethod
    def _fmt(q) -> str:
        return f'pan {math.degrees(q[0]):.1f} deg, tilt {math.degrees(q[1]):.1f} deg'

    def _to(self, phase: str, now: float) -> None:
        self.phase, self.t_phase = phase, now
        self.timeline.append((phase, now))

    def _not_ready(self) -> str:
        """Why the step cannot leave ``waiting`` yet ('' when it can): the right fixation centred and of one id for
        the last ``settle_frames`` frames, the left's own fixation likewise, and both heads calm (the rig is not
        turning faster than the servos follow, so the partner point is likely to settle)."""
        n = self.p.settle_frames
        right = [(px, i) for _, px, i in list(self.right_fix)[-n:]]
        for side, fixes in (('right', right), ('left', list(self._own)[-n:])):
            why = self._unsettled(side, fixes)
            if why:
                return why
        for side, history in (('right', self.right_history), ('left', self.left_history)):
            rate = self._rate(history)
            if rate is None or rate > math.radians(self.p.max_rate_deg_s):
                turning = 'no recent readings' if rate is None else f'turning {math.degrees(rate):.1f} deg/s'
                return f'{side} head {turning} (max_rate_deg_s {self.p.max_rate_deg_s:g})'
        return ''

    def _unsettled(self, side: str, fixes: list[tuple[tuple[float, float] | None, int]]) -> str:
        """Why ``side``'s newest (pixel, id) fixations are not ``settle_frames`` of one valid, centred point ('' when
        they are)."""
        if len(fixes) < self.p.settle_frames or len({i for _, i in fixes}) != 1 or any(px is None for px, _ in fixes):
            return f'{side} fixation changed, invalid or too few frames'
        off = max(math.dist(px, self.rig.camera(side).center) for px, _ in fixes)
        return f'{side} fixation {off:.0f} px from the centre (settle_px {self.p.settle_px:g})' \
            if not all(self._centred(side, px) for px, _ in fixes) else ''

    def _rate(self, history: JointHistory) -> float | None:
        """How fast the head turned (rad/s) over its latest readings; None without them."""
        latest = history.latest()
        if latest is None:
            return None
        m = self._motion(history, latest[0] - self.p.motion_window_s)
        return None if m is None else m[0]

    def _fail(self, now: float, reason: str) -> None:
        self.reason, self._ended = reason, 'failed'
        self._start_return(now)

    def _start_return(self, now: float) -> None:
        self.right_images.clear()
        self.t_phase = now
        if self.t_left is None:         # the head never left its own point: nothing to return from
            self._to('ended', now)
            self.finished = True
            return
        self._to('returning', now)
        self._aim, self._arrived, self.t_return = self.home, None, now

    def _reached(self, now: float, aim: tuple[float, float]) -> bool:
        latest = self.left_history.latest()
        tol = math.radians(self.p.aim_tolerance_deg)
        if latest is None or abs(latest[1] - aim[0]) > tol or abs(latest[2] - aim[1]) > tol:
            self._arrived = None
            return False
        if self._arrived is None:
            self._arrived = latest[0]
            self.timeline.append(('arrived', now))
        return True

    def _move_s(self, frm: tuple[float, float], to: tuple[float, float]) -> float:
        """How long a head move takes: its longer axis at the head's top speed, plus ``move_latency_s``."""
        return max(math.degrees(abs(to[k] - frm[k])) / self.p.slew_deg_s[k] for k in (0, 1)) + self.p.move_latency_s

    def _trip_s(self, frm: tuple[float, float], aim: tuple[float, float], home: tuple[float, float]) -> float:
        """Predicted interruption of a move ``frm`` -> ``aim`` (its latency covers the image searched there) and the
        move back ``home``."""
        return self._move_s(frm, aim) + self._move_s(aim, home)

    def _over_budget(self, now: float, aim: tuple[float, float]) -> str:
        """Why a move to ``aim`` now would take the step past ``max_interruption_s`` ('' when it would not)."""
        latest, home = self.left_history.latest(), self.home
        if latest is None or home is None:
            return ''
        spent = 0.0 if self.t_left is None else now - self.t_left
        total = spent + self._trip_s((latest[1], latest[2]), aim, home)
        if total <= self.p.max_interruption_s:
            return ''
        return (f'a move to {self._fmt(aim)} would interrupt the left fixation for {total:.2f} s ({spent:.2f} s '
                f'spent; more than max_interruption_s {self.p.max_interruption_s:g} s)')

    def _next_aim(self, now: float) -> None:
        while self._aims:
            aim = self._lead_aim(self._aims.pop(0), self._t_plan, now)
            if not self._reachable(aim):
                self._rejections.append(f"aim {self._fmt(aim)} beyond the left head's range (the rig turns)")
                continue
            over = self._over_budget(now, aim)
            if over:
                self._aims.clear()
                self._rejections.append(over)
                continue
            break
        else:
            why = '; '.join(self._rejections) or 'no aim covers the search range'
            # before the first move (no t_left yet): that aim, led for a turning rig, is beyond the range or the
            # bound the plan's aims were within, and the step ends without the head having moved
            self._fail(now, f'partner point not found ({why})' if self.t_left is not None else
                       f'too long a trip or out of range once led for the turning rig ({why})')
            return
        self._aim = aim
        self._arrived = None
        self.t_phase = now
        self.timeline.append(('aim', now))

    def _reachable(self, aim: tuple[float, float]) -> bool:
        if self.left_range is None:
            return True
        (p0, p1), (t0, t1) = self.left_range
        return p0 <= aim[0] <= p1 and t0 <= aim[1] <= t1

    def _plan_aims(self, ray_r: np.ndarray, home: tuple[float, float]) -> tuple[list[np.ndarray], str]:
        """The points along the right ray (rig frame) to aim the left head at, in its range and near enough
        ``home`` that the moves there and back fit ``max_interruption_s``: first the one at the prior depth (the
        match then lands near the centre: no centring move), then those covering the whole search range; or none
        and why. None either when the point lies so near the baseline's line that its vergence is below
        ``plan_angle_deg``: on an arc the heads turn towards that line, and a trigger the min interval held back
        came to a point already turned so far that the step measured nothing (the demo's second arc: vergence
        0.2-0.3 deg, docs/results.md "Stop 58")."""
        depth = self.p.prior_depth_m or math.sqrt(self.p.min_depth_m * self.p.max_depth_m)
        angle = math.degrees(ray_angle(ray_r * depth - self.rig.center('right'), ray_r * depth - self.rig.c_L))
        if angle < self.p.plan_angle_deg:
            return [], (f'the right fixation point lies nearly along the baseline (vergence {angle:.2f} deg at '
                        f'{depth:.1f} m < {self.p.plan_angle_deg:g} deg)')
        depths = vergence_aim_depths(self.rig, ray_r, self.p.min_depth_m, self.p.max_depth_m,
                                     margin_px=self.p.patch_half + 4)
        prior = self.p.prior_depth_m
        if prior is not None and self.p.min_depth_m < prior < self.p.max_depth_m:
            depths.insert(0, prior)
        points = [ray_r * d for d in depths]
        aims = [(x, self.rig.aim_readings('left', x)) for x in points]
        aims = [(x, a) for x, a in aims if self._reachable(a)]
        if not aims:
            return [], "the right fixation point is beyond the left head's range"
        trip = [self._trip_s(home, a, home) for _, a in aims]
        near = [x for (x, _), d in zip(aims, trip, strict=True) if d <= self.p.max_interruption_s]
        if not near:
            turn = min(max(abs(a[0] - home[0]), abs(a[1] - home[1])) for _, a in aims)
            return [], (f'the right fixation point is {math.degrees(turn):.0f} deg away from where the left head '
                        f'looks: too long a trip ({min(trip):.2f} s there and back, more than max_interruption_s '
                        f'{self.p.max_interruption_s:g} s)')
        return near, ''

    # -------------------------------------------------------------------- aims on a turning rig
    def _led(self, point: np.ndarray, t_seen: float, t_then: float) -> np.ndarray:
        """Where a static scene point seen at ``point`` (rig frame) at ``t_seen`` will be at ``t_then``. The right
        head holds its fixation point on its axis, so while the rig turns that point's direction turns with the
        head: the point is turned about the right camera by the head's rotation from ``t_seen`` to ``t_then``,
        extrapolated at its latest rate (at rest: the point itself). The rig's translation is left out (a few mm
        over a move, against metres of depth)."""
        rate = self.right_history.rate(self.p.lead_window_s)
        if rate is None or (rate[1] == 0.0 and rate[2] == 0.0):
            return point
        t0, rp, rt = rate
        q0 = self.right_history.at(t0, max_extrapolation_s=0.0)     # the reading the rate ends at
        if q0 is None:
            return point

        def rot(t: float) -> np.ndarray:
            return self.rig.cam_to_rig('right', q0[0] + rp * (t - t0), q0[1] + rt * (t - t0))

        c = self.rig.center('right')
        return c + rot(t_then) @ rot(t_seen).T @ (np.asarray(point, float) - c)

    def _lead_aim(self, point: np.ndarray, t_seen: float, now: float) -> tuple[float, float]:
        """Left joint readings that put ``point`` (seen at ``t_seen``) on the left axis when a move started
        ``now`` ends: the move's duration is the turn at ``slew_deg_s`` (per axis) plus ``move_latency_s``, and
        the point turns meanwhile (:meth:`_led`)."""
        aim = self.rig.aim_readings('left', point)
        latest = self.left_history.latest()
        for _ in range(2):      # the duration depends on the aim: one refinement is enough
            move = self.p.move_latency_s if latest is None else self._move_s((latest[1], latest[2]), aim)
            aim = self.rig.aim_readings('left', self._led(point, t_seen, now + move))
        return aim

    # -------------------------------------------------------------------- the left camera's frames
    def _action(self) -> Action:
        if self.phase in ('aiming', 'centring', 'returning') and self._aim is not None:
            return Action('hold', aim=self._aim)
        return Action('track')

    def on_left_image(self, t: float, gray: np.ndarray, now: float, right_fixated: bool = True) -> Action:
        """Call for each left image (before tracking). ``now``: the node's clock (same time base as stamps);
        ``right_fixated``: whether the right camera's newest fixation message has a fixation."""
        if self.t_start is None:
            self.t_start = self.t_phase = now
        self.poll(now)
        if self.phase == 'waiting':
            self._waiting_for = self._not_ready()
            trip = self._right_triple()
            home = self.left_history.latest()
            if trip is None or home is None or self._waiting_for:
                self._waiting_for = self._waiting_for or 'a right image with its fixation and joints'
                return Action('track')
            tr, _, rpx, rid, rq = trip
            self._right_id = rid
            self._aims, why = self._plan_aims(_right_ray(self.rig, rpx, rq), (home[1], home[2]))
            self._t_plan = tr
            if not self._aims:      # decided before the head leaves its own point
                self._fail(now, why)
                return Action('track')
            self.home = (home[1], home[2])
            self._to('aiming', now)
            self._next_aim(now)
            if not self._ended:         # the first aim is chosen: the head leaves its own point now
                self.t_left = now
            return self._action()
        if self.phase in ('aiming', 'centring'):
            return self._search(t, gray, now)
        if self.phase == 'returning':
            assert self._aim is not None
            # own point again as soon as the head is back (the tracker needs no settled image to select), or at
            # once, where the head is, when the right camera has no fixation either (swinging back from a limit,
            # re-selecting): with neither camera fixated the estimator has no rays to place the frames with
            back = self._reached(now, self._aim) and t >= self._arrived
            if back or not right_fixated or now - self.t_phase > self.p.aim_timeout_s:
                if not back and not right_fixated:
                    self.timeline.append(('return cut short', now))
                self._to('ended', now)
                self.finished, self.t_back = True, now
                return Action('track', reselect=True)
            return self._action()
        return Action('track')

    def _search(self, t: float, gray: np.ndarray, now: float) -> Action:
        """Aiming/centring: search on an image taken after the head arrived; a match far from the centre is
        first centred by a direct head move (too fast for the tracker), then found again near the centre."""
        assert self._aim is not None
        if not self._reached(now, self._aim) or t < self._arrived + self.p.aim_settle_s:
            if now - self.t_phase > self.p.aim_timeout_s:
                if self.phase == 'centring':
                    self._fail(now, 'the head did not reach the partner point')
                else:
                    self._rejections.append(f'head did not reach the aim {self._fmt(self._aim)} (at '
                                            f'{self._fmt(self.left_history.latest()[1:])})')
                    self._next_aim(now)
            return self._action()
        lq = self.left_history.at(t, max_extrapolation_s=0.1)
        trip = self._right_triple()
        if lq is None or trip is None:
            return self._action()
        tr, rimg, rpx, rid, rq = trip
        if rid != self._right_id:
            self._fail(now, 'the right camera re-selected its fixation point')
            return self._action()
        m = find_partner_point(rimg, rpx, rq, gray, lq, self.rig, self.p)
        self.match = m
        self.timeline.append(('searched' if m.ok else 'not found', now))
        if not m.ok:
            if self.phase == 'centring':
                self._fail(now, f'partner point not found again after centring it ({m.reason})')
            else:
                self._rejections.append(m.reason)
                self._next_aim(now)
            return self._action()
        cam = self.rig.left
        point = _right_ray(self.rig, rpx, rq) * m.depth_m       # the match, in the rig frame at tr
        if math.hypot(m.pixel[0] - cam.cx, m.pixel[1] - cam.cy) > self.p.select_px:
            if self.phase == 'centring':
                self._fail(now, 'the partner point is not near the centre after centring it')
                return self._action()
            aim = self._lead_aim(point, tr, now)
            if not self._reachable(aim):
                self._fail(now, "the partner point is beyond the left head's range")
                return self._action()
            over = self._over_budget(now, aim)
            if over:
                self._fail(now, f'the partner point is not centred: {over}')
                return self._action()
            self._to('centring', now)
            self._arrived, self._aim = None, aim
            return self._action()
        self._to('converging', now)
        self.t_fixating = now
        self.right_images.clear()
        dt = 0.1
        a, b = (self.rig.aim_readings('left', self._led(point, tr, t + k * dt)) for k in (0, 1))
        return Action('track', select=m.pixel, rate=((b[0] - a[0]) / dt, (b[1] - a[1]) / dt))

    def on_left_fixation(self, t: float, pixel: tuple[float, float] | None, fixation_id: int,
                         reselected: bool) -> None:
        """Call after tracking each left frame (waiting: the left's own point; converging: the partner point)."""
        if self.phase == 'waiting':
            self._own.append((pixel, fixation_id))
            return
        if self.phase != 'converging':
            return
        if self._left_id is None and reselected:
            self._left_id = fixation_id
        self.left_frames.append(_Frame(t, pixel, fixation_id))

    # -------------------------------------------------------------------- timeouts, measurement
    def poll(self, now: float) -> VergenceResult | None:
        """Timeouts, and the measurement once both fixations have settled. Returns the result once."""
        if self.phase == 'returning' and now - self.t_phase > self.p.aim_timeout_s:
            # no image came to end the return (on_left_image does that): end it here, the caller re-selects
            self._to('ended', now)
            self.finished, self.t_back, self.needs_reselect = True, now, True
        if self.t_start is None:        # the step's clock starts at its first poll or image
            self.t_start = self.t_phase = now
        if self._ended:
            return None
        if self.phase == 'waiting':
            if now - self.t_start > self.p.wait_timeout_s:
                self._fail(now, f'both fixations not settled within {self.p.wait_timeout_s:g} s (last: '
                                f'{self._waiting_for or "no left image"})')
            return None
        if self.t_left is not None and now - self.t_left > self.p.timeout_s:
            note = f' ({self._note})' if self._note else ''
            if self._rejections:
                note += f' [{"; ".join(self._rejections)}]'
            self._fail(now, f'timeout after {self.p.timeout_s:g} s in phase {self.phase}{note}')
            return None
        if self.phase != 'converging':
            return None
        frames = list(self.left_frames)
        # the point is gone (the left lost it or the right re-selected): measure with the frames before, if enough
        ended, why = math.inf, ''
        if frames and (frames[-1].pixel is None or frames[-1].fixation_id != self._left_id):
            ended = next(f.t for f in frames if f.pixel is None or f.fixation_id != self._left_id)
            why = 'the left camera lost the partner point'
        t_right = [f[0] for f in self.right_fix if frames and f[0] >= frames[0].t and f[2] != self._right_id]
        if t_right and min(t_right) < ended:
            ended, why = min(t_right), 'the right camera re-selected its fixation point'
        samples = self._samples([f for f in frames if f.t < ended])
        if why:
            if len(samples) < self.p.settle_frames:
                self._fail(now, why)
                return None
            self.timeline.append(('cut short', now))
            return self._measure(samples, now)
        if samples and self._t_settled is None:
            self._t_settled = now
            self.timeline.append(('settled', now))
        if self._t_settled is None and now - self.t_phase > self.p.hold_timeout_s:
            note = f' ({self._note})' if self._note else ''
            self._fail(now, f'the fixations did not settle within {self.p.hold_timeout_s:g} s{note}')
            return None
        # both heads standing still over the last settle_frames frames read exactly where they stand, and the
        # pixel part is one correspondence (average_samples): more frames would add nothing, only interruption
        n = min(self.p.frames, self.p.settle_frames)
        still = len(samples) >= n and not any(any(s.moving) for s in samples[-n:])
        enough = len(samples) >= self.p.frames or still or (
            self._t_settled is not None and now - self._t_settled > self.p.hold_timeout_s and len(samples) >= n)
        if not enough:
            if not samples and not self._note:
                self._note = 'no left frame matched with a right fixation and both joint states'
            return None
        return self._measure(samples, now)

    def _measure(self, samples: list[VergenceSample], now: float) -> VergenceResult | None:
        avg = average_samples(samples, self.rig.c_L, self.p.pixel_sigma_px / self.rig.left.fx,
                              math.radians(self.p.joint_sigma_deg), math.radians(self.p.min_angle_deg),
                              self.p.max_scatter, self.p.timing_sigma_s, self.p.timing_bias_s, self.p.max_rel_std)
        if not avg.ok:
            self._fail(now, avg.reason)
            return None
        assert avg.point_rig is not None and avg.cov_rig is not None
        self.result = VergenceResult(avg.t, avg.point_rig, avg.distance_m, avg.std_m, avg.angle_rad, avg.cov_rig,
                                     avg.right_pixel, avg.left_pixel, self.match, now - self.t_start, avg.frames,
                                     avg.distinct_readings, avg.scatter_m, avg.rate_mps)
        self._ended = 'done'
        self._start_return(now)
        return self.result

    def _motion(self, history: JointHistory, t: float) -> tuple[float, bool] | None:
        """(angular speed in rad/s, moved at all) of a head around ``t``; None until readings cover the window."""
        h = self.p.motion_window_s
        a, b = history.at(t - h, max_extrapolation_s=0.0), history.at(t + h, max_extrapolation_s=0.0)
        if a is None or b is None:
            return None
        step = math.hypot(b[0] - a[0], b[1] - a[1])
        return step / (2 * h), step > 1e-9

    def _frame_sample(self, f: _Frame) -> VergenceSample | str | None:
        """The sample of a left frame, or why it is not settled (a note), or None while its data is incomplete
        (partner message, readings after it). Final answers are cached: polls repeat this for every frame."""
        hit = self._sample_cache.get(f.t)
        if hit is not None:
            return hit
        rf = self._right_fix_near(f.t)
        if rf is None or rf[2] != self._right_id:
            return None
        lq = self.left_joints(f.t)
        rq = self.right_history.at(rf[0], max_extrapolation_s=0.0)
        rm, lm = self._motion(self.right_history, rf[0]), self._motion(self.left_history, f.t)
        if lq is None or rq is None or rm is None or lm is None:
            return None
        max_rate = math.radians(self.p.max_rate_deg_s)
        out: VergenceSample | str
        if not (self._centred('left', f.pixel) and self._centred('right', rf[1])) or max(rm[0], lm[0]) > max_rate:
            out = (f'fixations {math.dist(f.pixel, self.rig.left.center):.1f} px (left) and '
                   f'{math.dist(rf[1], self.rig.right.center):.1f} px (right) from the principal points, heads turning '
                   f'{math.degrees(lm[0]):.1f} (left) and {math.degrees(rm[0]):.1f} deg/s (right)')
        else:
            ray_r = _right_ray(self.rig, rf[1], rq)
            ray_l = self.rig.pixels_to_rig_rays('left', np.asarray(f.pixel, float).reshape(1, 2), *lq)[0]
            angle = ray_angle(ray_r, ray_l)
            if angle < math.radians(self.p.min_angle_deg):
                # on an arc the heads turn towards the baseline's line, and the rays with them: the frames
                # before still measure, so this one is left out rather than failing the step
                out = f'rays nearly parallel (vergence {math.degrees(angle):.2f} deg < {self.p.min_angle_deg:g} deg)'
            else:
                out = VergenceSample(f.t, ray_r, ray_l, (lq[0], lq[1], rq[0], rq[1]), rf[1], f.pixel,
                                     (rm[0], lm[0]), (rm[1], lm[1]))
        newest = self.right_fix[-1][0] if self.right_fix else -math.inf
        if abs(rf[0] - f.t) < 1e-6 or newest > f.t + self.p.stamp_slop_s:    # no closer partner message can come
            self._sample_cache[f.t] = out
        return out

    def _samples(self, frames: list[_Frame]) -> list[VergenceSample]:
        """Frames (oldest first) from the first run of ``settle_frames`` consecutive settled ones on: both fixations
        within ``settle_px`` of their principal points and both heads turning at most ``max_rate_deg_s``. A frame
        still lacking its partner message or readings after it, or whose joint state was dropped, is skipped; an
        unsettled one ends a run before the fixations have settled, and is left out after."""
        out: list[VergenceSample] = []
        run = 0
        for f in frames:
            if f.pixel is None:
                continue
            sample = self._frame_sample(f)
            if sample is None:
                continue
            if isinstance(sample, str):
                self._note = sample
                if run < self.p.settle_frames:
                    out, run = [], 0
                continue
            out.append(sample)
            run += 1
        return out if run >= self.p.settle_frames else []


# ------------------------------------------------------------------------------------------------ scheduler
@dataclass
class VergenceSchedule:
    period_s: float = 0.0          # > 0: a step at least this often (from the start of the last one)
    min_interval_s: float = 2.0    # from the end of one step to the start of the next, whatever triggers it
    retry_s: float = 5.0           # after a failure, retry this much later (doubled per failure in a row) ...
    retry_max_s: float = 60.0      # ... up to this


TRIGGERS = ('start', 'right_fixation', 'request', 'period', 'retry')


class VergenceScheduler:
    """Decides when the left camera runs a vergence step: at start-up, when the right camera selects a new
    fixation point (its id changes), when asked (a request), periodically, and after a failure (back-off) -
    never closer than ``min_interval_s`` after the previous step that left the own point, so the left camera's
    own fixation is interrupted for a bounded share of the time. A trigger during the min interval waits
    (triggers coalesce). One arriving while a step runs is ignored and counted, except a request: it asks for a
    measurement made after it (the estimator or ``fixego demo`` may have reset and forgotten the running step's),
    so it waits for the next step, unless the running step's measurement is stamped after the request came (then
    that one answers it: the estimator asked before it had received the start-up measurement, and the left head
    measured the same point again at rest, docs/results.md "Stop 56"). Plain data in, no clock of its own."""

    def __init__(self, params: VergenceSchedule | None = None, now: float = 0.0) -> None:
        self.p = params or VergenceSchedule()
        self.pending: str | None = 'start'
        self.running = False
        self.t_created = now
        self.t_last_start: float | None = None
        self.t_last_end: float | None = None
        self.t_retry: float | None = None
        self.failures_in_a_row = 0
        self.right_id: int | None = None
        self.triggers: dict[str, int] = dict.fromkeys(TRIGGERS, 0)
        self.triggers['start'] = 1
        self.t_request: float | None = None     # when the newest request came while a step ran
        self.answered = 0                       # such requests the running step's measurement answered
        self.ignored = 0
        self.attempts = self.successes = self.failures = 0
        self.last_trigger = ''

    def trigger(self, reason: str, now: float) -> bool:
        """A reason for a step; False (and counted as ignored) while a step runs, but for a request, which then
        waits for the next step."""
        self.triggers[reason] = self.triggers.get(reason, 0) + 1
        if self.running and reason == 'request':
            self.pending, self.t_request = reason, now
            return True
        if self.running:
            self.ignored += 1
            return False
        self.pending = self.pending or reason
        return True

    def on_right_fixation(self, fixation_id: int, now: float) -> bool:
        """The right camera's fixation id from its fixation topic: a new id (not the first seen) triggers. A negative
        id ("no valid fixation at this stamp") is no fixation point: ignored, the id before it is kept."""
        if fixation_id < 0:
            return False
        prev, self.right_id = self.right_id, int(fixation_id)
        if prev is None or prev == self.right_id:
            return False
        return self.trigger('right_fixation', now)

    def next_allowed(self) -> float:
        """Earliest time the next step may start (min interval)."""
        return -math.inf if self.t_last_end is None else self.t_last_end + self.p.min_interval_s

    def due(self, now: float) -> str | None:
        """The reason to start a step now, or None."""
        if self.running or now < self.next_allowed():
            return None
        if self.pending:
            return self.pending
        if self.t_retry is not None and now >= self.t_retry:
            return 'retry'
        since = self.t_last_start if self.t_last_start is not None else self.t_created
        if self.p.period_s > 0 and now - since >= self.p.period_s:
            return 'period'
        return None

    def started(self, reason: str, now: float) -> None:
        if reason in ('retry', 'period'):
            self.triggers[reason] += 1
        self.running, self.pending, self.t_retry = True, None, None
        self.attempts += 1
        self.last_trigger, self.t_last_start = reason, now

    def finished(self, ok: bool, now: float, left_own_point: bool = True, measured_at: float | None = None) -> None:
        """The step is over (head back): success, or a failure to retry after the back-off. The min interval
        runs from the end of the last step that took the left head off its own point (one that failed before,
        e.g. waiting for settled fixations, interrupted nothing). ``measured_at``: the stamp of the step's
        measurement; one at or after a request that came during the step answers it."""
        self.running = False
        if ok and self.t_request is not None and measured_at is not None and measured_at >= self.t_request:
            self.pending = None
            self.answered += 1
        self.t_request = None
        if left_own_point:
            self.t_last_end = now
        if ok:
            self.successes += 1
            self.failures_in_a_row = 0
            self.t_retry = None
        else:
            self.failures += 1
            self.failures_in_a_row += 1
            backoff = min(self.p.retry_s * 2 ** (self.failures_in_a_row - 1), max(self.p.retry_max_s, self.p.retry_s))
            self.t_retry = now + backoff
