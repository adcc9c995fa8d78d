"""Sliding-window refinement of the recent keyframe poses together with persistent landmarks (ROS-free).

Why: the two-frame constraints fix the metric scale only through the left camera's lever arm, which
vanishes on straight segments (DESIGN.md §5). Static points that stay in view -- each camera's fixation
point for as long as it lasts, and long-lived flow tracks -- carry the scale seen during turns through
the straights once their positions are part of the estimate. So this window keeps

- the last ``frames`` keyframe poses variable; older keyframes stay, *fixed*, for as long as a live
  landmark was seen from them, so the landmarks they anchor keep the metric scale of the past;
- a landmark per persistent track, triangulated once its rays span ``min_parallax_deg``; a new landmark
  (a newly selected fixation point too) takes its depth from the poses already estimated;

and minimises, by Levenberg-Marquardt with the landmarks eliminated through the Schur complement,

- the robust (Huber) tangent-plane reprojection error of every observation (angular, in units of the
  ray noise ``sigma``; for a pan/tilt camera with rays in the rig frame this is the pixel error / f),
- a factor per consecutive keyframe pair: the measured step (the two-frame solve) with its covariance,
  down-weighted by ``step_weight`` because its flow points are partly the same observations,
- optional scale aids: a translation factor from an external speed source, and a position prior on
  a landmark (the start-up vergence distance of a fixation point).

Landmark keys are int64 values built by :func:`landmark_key` (track or fixation, camera, id), so the
observations of a frame can be matched with numpy alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from fixego_ros.geometry.rotation import Pose, exp_so3, log_so3, project_to_so3

TRACK, FIXATION = 0, 1


def landmark_key(kind: int, side_index: int, ident: np.ndarray | int) -> np.ndarray:
    """Landmark key(s) of a track (``kind`` TRACK) or a fixation point (FIXATION) of camera
    ``side_index`` (0 right, 1 left) with the given id(s)."""
    return (np.asarray(ident, dtype=np.int64) * 2 + side_index) * 2 + kind


def landmark_kind_side(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kind (TRACK / FIXATION) and camera index of landmark keys (the inverse of :func:`landmark_key`)."""
    keys = np.asarray(keys, dtype=np.int64)
    return keys % 2, (keys // 2) % 2


@dataclass(frozen=True)
class WindowConfig:
    """Options of the sliding window (defaults suit ~5-30 keyframes/s and ~80 tracks per camera). The defaults
    are estimator_node's (``pipeline.params``); ``sigma`` is its pixel_sigma over the default rig's focal length
    (config/rig.yaml: 1727 px)."""

    frames: int = 4                    # keyframe poses refined (the newest ones)
    max_fixed_frames: int = 12         # older keyframes kept (fixed) for their observations of live landmarks
    max_unobserved_frames: int = 40    # while the scale is unobserved the window grows up to this
    iterations: int = 4                # LM iterations per keyframe
    sigma: float = 1.0 / 1727.0        # angular noise of one ray (rad)
    huber: float = 2.0                 # Huber knee in sigmas
    outlier_sigma: float = 8.0         # a landmark with an observation this far off is dropped
    min_parallax_deg: float = 1.0      # triangulate a landmark once its rays span this angle
    min_depth_m: float = 0.1
    max_depth_m: float = 100.0
    step_weight: float = 0.5           # information of the two-frame step factor relative to its covariance

    def __post_init__(self) -> None:
        if self.frames < 2:
            raise ValueError(f'frames must be >= 2, got {self.frames}')
        if self.max_unobserved_frames < self.frames:
            raise ValueError('max_unobserved_frames must be >= frames')
        if self.max_fixed_frames < 1 or self.iterations < 1:
            raise ValueError('max_fixed_frames and iterations must be >= 1')
        for name in ('sigma', 'huber', 'outlier_sigma', 'min_depth_m', 'max_depth_m'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')
        if not (self.step_weight >= 0.0 and math.isfinite(self.step_weight)):
            raise ValueError(f'step_weight must be finite and >= 0, got {self.step_weight}')


@dataclass
class StepFactor:
    """Measured motion from the previous keyframe (its rig frame) to this one, and its 6x6 covariance
    over [rotation vector, translation]; optionally a translation from an external speed source."""

    motion: Pose
    covariance: np.ndarray
    speed_t: np.ndarray | None = None      # translation (m) over the step from the speed source
    speed_cov: np.ndarray | None = None    # its 3x3 covariance


@dataclass
class _Frame:
    stamp: float
    R: np.ndarray
    p: np.ndarray
    keys: np.ndarray          # (n,) landmark keys observed here
    rays: np.ndarray          # (n, 3) rig-frame unit rays
    centers: np.ndarray       # (n, 3) camera centre of each ray (rig frame)
    basis: np.ndarray         # (n, 2, 3) tangent basis of each ray
    step: StepFactor | None
    prev_stamp: float | None      # the keyframe ``step`` starts from
    fixed: bool = False


@dataclass
class WindowStats:
    """What the last :meth:`SlidingWindow.add` did (for diagnostics and benchmarks)."""

    variable_frames: int = 0
    fixed_frames: int = 0
    landmarks: int = 0
    observations: int = 0
    new_landmarks: int = 0
    dropped_landmarks: int = 0
    iterations: int = 0
    cost_before: float = 0.0
    cost_after: float = 0.0


@dataclass
class _Prior:
    """Position of a landmark in the rig frame of one keyframe (a vergence measurement)."""

    stamp: float
    key: int
    point: np.ndarray
    information: np.ndarray


def _tangent_basis(rays: np.ndarray) -> np.ndarray:
    """(n, 2, 3) orthonormal vectors perpendicular to each unit ray."""
    helper = np.where(np.abs(rays[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(rays, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(rays, e1)
    return np.stack([e1, e2], axis=1)


def _skew_batch(v: np.ndarray) -> np.ndarray:
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def _lookup(lm_keys: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index into the sorted ``lm_keys`` of each of ``keys`` and whether it is there."""
    pos = np.minimum(np.searchsorted(lm_keys, keys), len(lm_keys) - 1)
    return pos, lm_keys[pos] == keys


def _point_jacobian(R: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(3, 6) derivative of ``z = R^T (X - p)`` over the pose [rotation (right perturbation), position]."""
    return np.hstack([_skew_batch(z[None])[0], -R.T])


def _information(cov: np.ndarray, weight: float = 1.0) -> np.ndarray:
    """Information matrix of a covariance (pseudo-inverse: unobserved directions carry none)."""
    cov = 0.5 * (cov + cov.T)
    w, V = np.linalg.eigh(cov)
    inv = np.where(w > 1e-12, 1.0 / np.maximum(w, 1e-12), 0.0)
    return weight * (V * inv) @ V.T


class SlidingWindow:
    """Keyframes in, refined poses out. Call :meth:`add` once per keyframe, oldest first."""

    def __init__(self, config: WindowConfig | None = None) -> None:
        self.config = config or WindowConfig()
        self.frames: list[_Frame] = []
        self.landmarks: dict[int, np.ndarray] = {}     # key -> world position
        self.dead: set[int] = set()                    # keys found to be outliers: never used again
        self.priors: list[_Prior] = []
        self.hold_open = True                          # scale unobserved: grow the window instead of fixing
        self.stats = WindowStats()

    # ---------------------------------------------------------------------------------------------- API
    def add(self, stamp: float, pose: Pose, keys: np.ndarray, rays: np.ndarray, centers: np.ndarray,
            step: StepFactor | None) -> Pose:
        """Add a keyframe at ``pose`` (initial guess, world = rig frame at the first keyframe) with its
        observations (landmark keys, rig-frame unit rays and the camera centre of each) and the factor
        linking it to the previous keyframe; refine; return its refined pose."""
        keys = np.asarray(keys, np.int64).reshape(-1)
        rays = np.asarray(rays, float).reshape(-1, 3)
        centers = np.asarray(centers, float).reshape(-1, 3)
        ok = np.all(np.isfinite(rays), axis=1) & np.all(np.isfinite(centers), axis=1)
        norms = np.linalg.norm(rays, axis=1)
        ok &= norms > 0.5
        keys, rays, centers = keys[ok], rays[ok] / norms[ok, None], centers[ok]
        keys, first = np.unique(keys, return_index=True)
        rays, centers = rays[first], centers[first]
        first_frame = not self.frames
        self.frames.append(_Frame(float(stamp), pose.R.copy(), pose.t.copy(), keys, rays, centers,
                                  _tangent_basis(rays) if len(rays) else np.zeros((0, 2, 3)),
                                  None if first_frame else step, None if first_frame else self.frames[-1].stamp,
                                  fixed=first_frame))
        self.stats = WindowStats()
        if not first_frame:
            self._locate_newest()
        self._slide()
        self._triangulate()
        if any(not f.fixed for f in self.frames):
            self._optimise()
        self._cull()
        self.stats.variable_frames = sum(not f.fixed for f in self.frames)
        self.stats.fixed_frames = len(self.frames) - self.stats.variable_frames
        self.stats.landmarks = len(self.landmarks)
        f = self.frames[-1]
        return Pose(f.R.copy(), f.p.copy())

    def add_prior(self, stamp: float, key: int, point_rig: np.ndarray, cov_rig: np.ndarray,
                  tolerance_s: float = 1e-6) -> bool:
        """Landmark ``key`` was at ``point_rig`` in the rig frame of the keyframe at ``stamp`` (a vergence
        measurement). False when no kept keyframe has that stamp or saw that landmark."""
        for f in self.frames:
            if abs(f.stamp - stamp) <= tolerance_s and int(key) in set(f.keys.tolist()):
                point = np.asarray(point_rig, float).reshape(3)
                info = _information(np.asarray(cov_rig, float).reshape(3, 3))
                if not (np.all(np.isfinite(point)) and np.all(np.isfinite(info))):
                    return False
                self.priors.append(_Prior(f.stamp, int(key), point, info))
                return True
        return False

    def prior_scale(self) -> float | None:
        """Ratio of the measured to the estimated distance of the landmarks with a position prior (median),
        once the window has placed them; None before."""
        frames = {f.stamp: f for f in self.frames}
        ratios = []
        for pr in self.priors:
            f, X = frames.get(pr.stamp), self.landmarks.get(pr.key)
            if f is None or X is None:
                continue
            est = float(np.linalg.norm(f.R.T @ (X - f.p)))
            if est > 1e-9:
                ratios.append(float(np.linalg.norm(pr.point)) / est)
        return float(np.median(ratios)) if ratios else None

    def rescale(self, s: float) -> None:
        """Scale every position (keyframes and landmarks) about the world origin: a scale found late (a
        vergence distance) applied to what was built with an unobserved one."""
        for f in self.frames:
            f.p = f.p * s
        for key in self.landmarks:
            self.landmarks[key] = self.landmarks[key] * s

    def poses(self) -> list[tuple[float, Pose]]:
        """Stamp and current pose of every kept keyframe, oldest first."""
        return [(f.stamp, Pose(f.R.copy(), f.p.copy())) for f in self.frames]

    # ------------------------------------------------------------------------------------- bookkeeping
    def _slide(self) -> None:
        """Fix the oldest variable keyframes beyond the window length."""
        cfg = self.config
        limit = cfg.max_unobserved_frames if self.hold_open else cfg.frames
        variable = [f for f in self.frames if not f.fixed]
        for f in variable[:max(0, len(variable) - limit)]:
            f.fixed = True

    def _cull(self) -> None:
        """Forget landmarks nothing variable sees any more, and fixed keyframes nothing live was seen from."""
        newest = set(self.frames[-1].keys.tolist())
        seen_var: set[int] = set()
        for f in self.frames:
            if not f.fixed:
                seen_var.update(f.keys.tolist())
        for key in list(self.landmarks):
            if key not in seen_var:
                del self.landmarks[key]
                self.stats.dropped_landmarks += 1
        live = newest | set(self.landmarks)
        self.dead &= seen_var
        # drop fixed frames with no live observation, keeping the newest fixed one (it anchors the first
        # variable keyframe's step factor)
        fixed_idx = [i for i, f in enumerate(self.frames) if f.fixed]
        keep_anchor = fixed_idx[-1] if fixed_idx else -1
        kept: list[_Frame] = []
        for i, f in enumerate(self.frames):
            if f.fixed and i != keep_anchor and not (live & set(f.keys.tolist())):
                continue
            kept.append(f)
        fixed = [f for f in kept if f.fixed]
        while len(fixed) > self.config.max_fixed_frames:
            kept.remove(fixed.pop(0))
        self.frames = kept
        stamps = {f.stamp for f in self.frames}
        self.priors = [p for p in self.priors if p.stamp in stamps and (p.key in self.landmarks or p.key in newest)]

    def _triangulate(self) -> None:
        """Give a position to every landmark whose rays now span ``min_parallax_deg`` (midpoint of all
        its observations with the current poses), when every observation sees it in front."""
        cfg = self.config
        cand = set(self.frames[-1].keys.tolist()) - set(self.landmarks) - self.dead
        if not cand:
            return
        cand_arr = np.array(sorted(cand), np.int64)
        K, D, O = [], [], []
        for f in self.frames:
            m = np.isin(f.keys, cand_arr, assume_unique=True)
            if np.any(m):
                K.append(f.keys[m])
                D.append(f.rays[m] @ f.R.T)
                O.append(f.centers[m] @ f.R.T + f.p)
        k, d, o = np.concatenate(K), np.concatenate(D), np.concatenate(O)
        order = np.argsort(k, kind='stable')
        k, d, o = k[order], d[order], o[order]
        uniq, start, count = np.unique(k, return_index=True, return_counts=True)
        sel = count >= 2
        if not np.any(sel):
            return
        group = np.repeat(np.arange(len(uniq)), count)
        first = d[start][group]
        cos = np.einsum('ij,ij->i', d, first)
        min_cos = np.minimum.reduceat(cos, start)
        sel &= min_cos <= math.cos(math.radians(cfg.min_parallax_deg))
        if not np.any(sel):
            return
        P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]          # projector off each ray
        A = np.add.reduceat(P, start, axis=0)
        b = np.add.reduceat(np.einsum('nij,nj->ni', P, o), start, axis=0)
        det = np.linalg.det(A)
        sel &= det > 1e-12
        X = np.zeros((len(uniq), 3))
        X[sel] = np.linalg.solve(A[sel], b[sel][:, :, None])[:, :, 0]
        depth = np.einsum('ij,ij->i', X[group] - o, d)
        good_depth = (depth > cfg.min_depth_m) & (depth < cfg.max_depth_m)
        sel &= np.logical_and.reduceat(good_depth, start)
        for key, x in zip(uniq[sel].tolist(), X[sel], strict=True):
            self.landmarks[key] = x
        self.stats.new_landmarks = int(sel.sum())

    # ------------------------------------------------------------------------------------ optimisation
    def _locate_newest(self, min_points: int = 8) -> None:
        """Pose of the new keyframe against the landmarks already placed (they hold the scale so far):
        a few Gauss-Newton steps on its 6 DOF before the window is adjusted, so the adjustment starts from
        the scale the map carries rather than from the two-frame guess, whose scale is weak."""
        f = self.frames[-1]
        if not self.landmarks or not len(f.keys):
            return
        lm_keys = np.array(sorted(self.landmarks), np.int64)
        pos, m = _lookup(lm_keys, f.keys)
        if int(m.sum()) < min_points:
            return
        X = np.array([self.landmarks[int(k)] for k in lm_keys[pos[m]]])
        n = len(X)
        prob = {'fr': np.zeros(n, int), 'li': np.arange(n), 'rays': f.rays[m], 'cs': f.centers[m], 'bs': f.basis[m]}
        R, p = f.R[None].copy(), f.p[None].copy()
        for _ in range(self.config.iterations + 2):
            rw, J, _ = self._obs_jacobians(prob, R, p, X)
            H = np.einsum('nki,nkj->ij', J, J)
            g = np.einsum('nki,nk->i', J, rw)
            try:
                d = np.linalg.solve(H + 1e-6 * np.diag(np.diag(H)) + 1e-12 * np.eye(6), -g)
            except np.linalg.LinAlgError:
                return
            if not np.all(np.isfinite(d)):
                return
            R[0] = project_to_so3(R[0] @ exp_so3(d[:3]))
            p[0] = p[0] + d[3:]
            if np.linalg.norm(d) < 1e-9:
                break
        r = self._obs_residuals(prob, R, p, X)[0]
        inliers = np.linalg.norm(r, axis=1) <= self.config.outlier_sigma
        if int(inliers.sum()) >= min_points // 2 and np.all(np.isfinite(R)) and np.all(np.isfinite(p)):
            f.R, f.p = R[0], p[0]

    def _problem(self) -> dict:
        """Index arrays of the current problem (fixed over the LM iterations of one keyframe)."""
        var = [i for i, f in enumerate(self.frames) if not f.fixed]
        var_pos = {i: j for j, i in enumerate(var)}
        lm_keys = np.array(sorted(self.landmarks), np.int64)
        F, Ks, Rays, Cs, Bs = [], [], [], [], []
        for i, f in enumerate(self.frames):
            if not len(f.keys) or not len(lm_keys):
                continue
            pos, m = _lookup(lm_keys, f.keys)
            if not np.any(m):
                continue
            F.append(np.full(int(m.sum()), i))
            Ks.append(pos[m])
            Rays.append(f.rays[m])
            Cs.append(f.centers[m])
            Bs.append(f.basis[m])
        if F:
            fr, li = np.concatenate(F), np.concatenate(Ks)
            rays, cs, bs = np.concatenate(Rays), np.concatenate(Cs), np.concatenate(Bs)
        else:
            fr = li = np.zeros(0, int)
            rays = cs = np.zeros((0, 3))
            bs = np.zeros((0, 2, 3))
        # only landmarks seen from a variable frame are unknowns; others are constants
        fpos = np.array([var_pos.get(i, -1) for i in range(len(self.frames))], int)
        seen = np.zeros(len(lm_keys), bool)
        if len(fr):
            seen[li[fpos[fr] >= 0]] = True
            seen &= np.bincount(li, minlength=len(lm_keys)) >= 2     # one ray leaves the depth free
        lm_pos = np.cumsum(seen) - 1
        keep = seen[li] if len(li) else np.zeros(0, bool)
        return {'var': var, 'fpos': fpos, 'lm_keys': lm_keys[seen], 'fr': fr[keep], 'li': lm_pos[li[keep]],
                'rays': rays[keep], 'cs': cs[keep], 'bs': bs[keep]}

    def _state(self, prob: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        R = np.stack([f.R for f in self.frames])
        p = np.stack([f.p for f in self.frames])
        X = np.array([self.landmarks[int(k)] for k in prob['lm_keys']]).reshape(-1, 3)
        return R, p, X

    def _obs_residuals(self, prob: dict, R: np.ndarray, p: np.ndarray, X: np.ndarray):
        fr, li = prob['fr'], prob['li']
        Rf = R[fr]
        z = np.einsum('nji,nj->ni', Rf, X[li] - p[fr])              # R^T (X - p)
        y = z - prob['cs']
        depth = np.einsum('ni,ni->n', prob['rays'], y)
        safe = np.where(depth > 1e-6, depth, 1e-6)
        r = np.einsum('nki,ni->nk', prob['bs'], y) / safe[:, None] / self.config.sigma
        r[depth <= 1e-6] = 1e3                                     # behind the camera: a bounded large error
        return r, z, safe, depth > 1e-6

    def _cost(self, prob: dict, R: np.ndarray, p: np.ndarray, X: np.ndarray) -> float:
        r = self._obs_residuals(prob, R, p, X)[0]
        s = np.linalg.norm(r, axis=1)
        k = self.config.huber
        cost = float(np.sum(np.where(s <= k, s * s, 2 * k * s - k * k)))
        for res, _, W in self._factors(prob, R, p, X, jacobians=False):
            cost += float(res @ W @ res)
        return 0.5 * cost

    def _factors(self, prob: dict, R: np.ndarray, p: np.ndarray, X: np.ndarray, jacobians: bool = True):
        """(residual, {frame index or ('l', landmark index): Jacobian}, information) per factor."""
        for b in range(1, len(self.frames)):
            fa, fb = self.frames[b - 1], self.frames[b]
            st = fb.step
            if st is None or fb.prev_stamp != fa.stamp or (fa.fixed and fb.fixed):
                continue
            Ra, Rb, pa, pb = R[b - 1], R[b], p[b - 1], p[b]
            RD = Ra.T @ Rb
            tD = Ra.T @ (pb - pa)
            res = np.concatenate([log_so3(st.motion.R.T @ RD), tD - st.motion.t])
            W = _information(st.covariance, self.config.step_weight)
            J = {}
            if jacobians:
                Ja = np.zeros((6, 6))
                Ja[:3, :3] = -RD.T
                Ja[3:] = _point_jacobian(Ra, tD)
                Jb = np.zeros((6, 6))
                Jb[:3, :3] = np.eye(3)
                Jb[3:, 3:] = Ra.T
                J = {b - 1: Ja, b: Jb}
            yield res, J, W
            if st.speed_t is not None and st.speed_cov is not None:
                res = tD - st.speed_t
                W = _information(st.speed_cov)
                J = {}
                if jacobians:
                    J = {b - 1: _point_jacobian(Ra, tD), b: np.hstack([np.zeros((3, 3)), Ra.T])}
                yield res, J, W
        if not self.priors:
            return
        index = {f.stamp: i for i, f in enumerate(self.frames)}
        lm_index = {int(k): j for j, k in enumerate(prob['lm_keys'])}
        for pr in self.priors:
            i, j = index.get(pr.stamp), lm_index.get(pr.key)
            if i is None or j is None:
                continue
            z = R[i].T @ (X[j] - p[i])
            res = z - pr.point
            J = {}
            if jacobians:
                J = {i: _point_jacobian(R[i], z), ('l', j): R[i].T}
            yield res, J, pr.information

    def _obs_jacobians(self, prob: dict, R: np.ndarray, p: np.ndarray, X: np.ndarray):
        """Huber-weighted (IRLS) residuals (n, 2) and their Jacobians over each observation's pose (n, 2, 6)
        and landmark (n, 2, 3)."""
        r, z, depth, front = self._obs_residuals(prob, R, p, X)
        s = np.linalg.norm(r, axis=1)
        k = self.config.huber
        sw = np.sqrt(np.where(s <= k, 1.0, k / np.maximum(s, 1e-12)) * front)
        A = (prob['bs'] - r[:, :, None] * self.config.sigma * prob['rays'][:, None, :]) / depth[:, None, None]
        A /= self.config.sigma
        Jl = np.einsum('nki,nji->nkj', A, R[prob['fr']]) * sw[:, None, None]    # d r / d X = A R^T
        Jt = np.cross(A, z[:, None, :]) * sw[:, None, None]                     # d r / d theta = A [z]x
        return r * sw[:, None], np.concatenate([Jt, -Jl], axis=2), Jl

    def _linearise(self, prob: dict, R: np.ndarray, p: np.ndarray, X: np.ndarray):
        """Normal equations: dense pose block (6V x 6V), landmark blocks (L,3,3), coupling (V,L,6,3)."""
        V, L = len(prob['var']), len(X)
        fpos = prob['fpos']
        fr, li = prob['fr'], prob['li']
        rw, Jp, Jl = self._obs_jacobians(prob, R, p, X)
        Hpp = np.zeros((V * 6, V * 6))
        gp = np.zeros(V * 6)
        Hll = np.zeros((L, 3, 3))
        gl = np.zeros((L, 3))
        Hpl = np.zeros((V, L, 6, 3))
        np.add.at(Hll, li, np.einsum('nki,nkj->nij', Jl, Jl))
        np.add.at(gl, li, np.einsum('nki,nk->ni', Jl, rw))
        vf = fpos[fr]
        on = vf >= 0
        if np.any(on):
            blocks = np.zeros((V, 6, 6))
            np.add.at(blocks, vf[on], np.einsum('nki,nkj->nij', Jp[on], Jp[on]))
            for j in range(V):
                Hpp[6 * j:6 * j + 6, 6 * j:6 * j + 6] += blocks[j]
            g = np.zeros((V, 6))
            np.add.at(g, vf[on], np.einsum('nki,nk->ni', Jp[on], rw[on]))
            gp += g.reshape(-1)
            Hpl[vf[on], li[on]] = np.einsum('nki,nkj->nij', Jp[on], Jl[on])
        for res, J, W in self._factors(prob, R, p, X):
            items = [(key, Jk) for key, Jk in J.items() if not isinstance(key, int) or fpos[key] >= 0]
            for ka, Ja in items:
                WJa = W @ Ja
                if isinstance(ka, tuple):
                    gl[ka[1]] += Ja.T @ W @ res
                else:
                    gp[6 * fpos[ka]:6 * fpos[ka] + 6] += Ja.T @ W @ res
                for kb, Jb in items:
                    blk = Jb.T @ WJa          # (db, da)
                    if isinstance(ka, tuple) and isinstance(kb, tuple):
                        Hll[ka[1]] += blk
                    elif isinstance(kb, tuple):             # rows landmark, cols pose a
                        Hpl[fpos[ka], kb[1]] += blk.T
                    elif isinstance(ka, tuple):
                        pass                                 # the symmetric half, added above
                    else:
                        ia, ib = 6 * fpos[ka], 6 * fpos[kb]
                        Hpp[ib:ib + 6, ia:ia + 6] += blk
        return Hpp, gp, Hll, gl, Hpl

    def _optimise(self) -> None:
        prob = self._problem()
        R, p, X = self._state(prob)
        var = prob['var']
        V, L = len(var), len(X)
        self.stats.observations = len(prob['fr'])
        cost = self._cost(prob, R, p, X)
        self.stats.cost_before = cost
        lam = 1e-4
        for _ in range(self.config.iterations):
            Hpp, gp, Hll, gl, Hpl = self._linearise(prob, R, p, X)
            improved = False
            for _try in range(6):
                dp, dl = self._solve(Hpp, gp, Hll, gl, Hpl, lam)
                if dp is None:
                    lam *= 10.0
                    continue
                R2, p2, X2 = R.copy(), p.copy(), X.copy()
                d = dp.reshape(V, 6)
                for j, i in enumerate(var):
                    R2[i] = project_to_so3(R[i] @ exp_so3(d[j, :3]))
                    p2[i] = p[i] + d[j, 3:]
                if L:
                    X2 = X + dl
                cost2 = self._cost(prob, R2, p2, X2)
                if np.isfinite(cost2) and cost2 < cost:
                    rel = (cost - cost2) / max(cost, 1e-12)
                    R, p, X, cost = R2, p2, X2, cost2
                    lam = max(lam * 0.3, 1e-9)
                    improved = True
                    break
                lam *= 10.0
            self.stats.iterations += 1
            if not improved or rel < 1e-6:
                break
        self.stats.cost_after = cost
        for i in var:
            self.frames[i].R, self.frames[i].p = R[i], p[i]
        for key, x in zip(prob['lm_keys'].tolist(), X, strict=True):
            self.landmarks[key] = x
        self._reject_outliers(prob, R, p, X)

    @staticmethod
    def _solve(Hpp, gp, Hll, gl, Hpl, lam):
        """Damped step by the Schur complement on the landmarks; (None, None) if singular."""
        V6 = len(gp)
        L = len(gl)
        Hd = Hpp + lam * np.diag(np.diag(Hpp)) + 1e-9 * np.eye(V6)
        if L:
            Hll_d = Hll + lam * Hll * np.eye(3)[None] + 1e-9 * np.eye(3)[None]
            try:
                Hll_inv = np.linalg.inv(Hll_d)
            except np.linalg.LinAlgError:
                return None, None
            Y = np.einsum('vlij,ljk->vlik', Hpl, Hll_inv)           # (V, L, 6, 3)
            Yr = Y.transpose(0, 2, 1, 3).reshape(V6, 3 * L)
            Pr = Hpl.transpose(0, 2, 1, 3).reshape(V6, 3 * L)
            S = Hd - Yr @ Pr.T
            rhs = gp - Yr @ gl.reshape(-1)
        else:
            S, rhs = Hd, gp
        try:
            dp = np.linalg.solve(0.5 * (S + S.T), -rhs)
        except np.linalg.LinAlgError:
            return None, None
        if not np.all(np.isfinite(dp)):
            return None, None
        if not L:
            return dp, np.zeros((0, 3))
        coupling = np.einsum('vlij,vi->lj', Hpl, dp.reshape(-1, 6))
        dl = np.einsum('lij,lj->li', Hll_inv, -gl - coupling)
        return dp, dl

    def _reject_outliers(self, prob: dict, R: np.ndarray, p: np.ndarray, X: np.ndarray) -> None:
        if not len(prob['fr']):
            return
        r = self._obs_residuals(prob, R, p, X)[0]
        bad = np.linalg.norm(r, axis=1) > self.config.outlier_sigma
        if not np.any(bad):
            return
        for key in set(prob['lm_keys'][prob['li'][bad]].tolist()):
            self.landmarks.pop(key, None)
            self.dead.add(key)
            self.stats.dropped_landmarks += 1


@dataclass
class SpeedSamples:
    """Velocity samples of an external source (rig frame, m/s) kept for the steps still to come."""

    stamps: list[float] = field(default_factory=list)
    v: list[np.ndarray] = field(default_factory=list)
    cov: list[np.ndarray] = field(default_factory=list)
    max_age_s: float = 0.5

    def add(self, stamp: float, v: np.ndarray, cov: np.ndarray) -> None:
        if self.stamps and stamp <= self.stamps[-1]:
            raise ValueError(f'speed sample at {stamp:.6f} not after the last one ({self.stamps[-1]:.6f})')
        self.stamps.append(float(stamp))
        self.v.append(np.asarray(v, float).reshape(3))
        self.cov.append(np.asarray(cov, float).reshape(3, 3))

    def translation(self, t0: float, t1: float, rotation: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Translation over [t0, t1] in the rig frame at ``t0``, from the samples in it (or the nearest within
        ``max_age_s``), with its covariance (errors taken as fully correlated over the interval: wheel slip is
        not white). ``rotation`` (rotation vector of the rig at ``t1`` in the rig at ``t0``) turns each sample
        from the rig frame at its stamp into the one at ``t0``, at constant angular velocity: on an arc the
        body-frame velocity stays forward while the step's chord turns by half the step's rotation, and a prior
        left in the wrong frame would bend the solved rotation to fit it."""
        if not self.stamps or t1 <= t0:
            return None
        s = np.asarray(self.stamps)
        dt = t1 - t0
        idx = np.flatnonzero((s >= t0 - 1e-9) & (s <= t1 + 1e-9))
        # where each sample lies in the step (its rig frame turned that far); the nearest one outside counts as mid-step
        if len(idx):
            frac = np.clip((s[idx] - t0) / dt, 0.0, 1.0)
        else:
            near = int(np.argmin(np.abs(s - 0.5 * (t0 + t1))))
            if abs(s[near] - 0.5 * (t0 + t1)) > self.max_age_s:
                return None
            idx, frac = np.array([near]), np.array([0.5])
        phi = np.zeros(3) if rotation is None else np.asarray(rotation, float).reshape(3)
        rots = [exp_so3(phi * f) for f in frac]
        v = np.mean([R @ self.v[i] for R, i in zip(rots, idx, strict=True)], axis=0)
        cov = np.mean([R @ self.cov[i] @ R.T for R, i in zip(rots, idx, strict=True)], axis=0)
        return v * dt, cov * dt * dt

    def forget_before(self, t: float) -> None:
        keep = [i for i, s in enumerate(self.stamps) if s >= t - self.max_age_s]
        self.stamps = [self.stamps[i] for i in keep]
        self.v = [self.v[i] for i in keep]
        self.cov = [self.cov[i] for i in keep]
