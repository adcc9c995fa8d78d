"""Incremental ego-motion estimator: two-frame solve per step, then local BA of the latest step.

Feed one :class:`FrameObservation` per synchronised frame; get a :class:`FrameResult` with the
refined pose (two-frame + local BA), the raw pose (two-frame only, the papers' comparison method), the
step covariance and a status. Memory is bounded by the BA window: only the last n frames' fixation
data and step motions are kept.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from fixego_ros.estimation.config import EstimatorConfig
from fixego_ros.estimation.constant_speed import ConstantSpeed
from fixego_ros.estimation.coplanarity import RayPairs
from fixego_ros.estimation.covariance import VAR_MAX, checked_measurement
from fixego_ros.estimation.frames import Fixation, FrameObservation, FrameResult, fixations_of, step_pairs
from fixego_ros.estimation.local_ba import BAProblem, BAResult, BATerm, refine_latest
from fixego_ros.estimation.scale_anchor import ScaleAnchor
from fixego_ros.estimation.speed_samples import SpeedSamples
from fixego_ros.estimation.status import StepStatus
from fixego_ros.estimation.twoframe import MIN_ROTATION_PAIRS, TwoFrameResult, TwoFrameSolver, kabsch_rotation
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.geometry.rotation import Pose, compose_all, rotation_angle


@dataclass
class _Slot:
    """What the window keeps of a keyframe."""

    fixation: dict[str, tuple[np.ndarray, int, np.ndarray] | None]
    step: Pose                      # refined motion into this keyframe from the previous one (identity first)


@dataclass
class _Latest:
    """The newest frame: it becomes a keyframe when the next observation's flow starts from it."""

    stamp: float
    fixation: dict[str, tuple[np.ndarray, int, np.ndarray] | None]
    motion: Pose                    # refined motion keyframe -> this frame
    motion_raw: Pose
    pose: Pose
    pose_raw: Pose
    pose_cov: np.ndarray
    step_cov: np.ndarray = field(default_factory=lambda: np.diag([1e-2] * 3 + [VAR_MAX] * 3))  # of ``motion``
    blind: _Blind | None = None     # the motion was predicted: re-estimated once the next step is solved


@dataclass
class _Blind:
    """A predicted step (nothing seen across it), kept to be re-estimated from the rates on both sides."""

    start: Pose                     # keyframe poses (refined, raw) the step starts from
    start_raw: Pose
    dt: float
    rate: tuple[np.ndarray, np.ndarray]   # [rvec, t] per second before it (refined, raw)


def _motion_at(rate: np.ndarray, dt: float) -> Pose:
    """The motion over ``dt`` at a constant ``rate`` ([rotation vector, translation] per second)."""
    return Pose.from_rvec(rate[:3] * dt, rate[3:] * dt)


# frames kept for a vergence measurement that arrives after its frame (~10 s at 10 Hz)
ANCHOR_HISTORY = 100


class Estimator:
    """Stateful incremental estimator (one instance per trajectory; :meth:`reset` restarts).

    Each observation's flow starts at a reference frame (``obs.prev_stamp``; the previous frame when
    None). The estimator solves the motion from that reference (a *keyframe*) to the new frame, so a
    front end may keep one reference over several frames and give the solver a usable baseline at a
    high frame rate; the newest frame becomes a keyframe when the observation says so
    (``obs.keyframe``), or else as soon as a later flow starts from it. The local BA refines only
    frames that become keyframes, since only their motion carries on into the trajectory. With
    ``prev_stamp`` always the previous frame, every frame is a keyframe (the papers' scheme).

    This is the papers' method (``refinement: local``, ``fixego paper-sim``, and the raw comparison): the local BA
    of the latest step over the last n keyframes. The metric back end is :class:`~.smoother.Smoother`. The metric
    scale is reported unobserved
    (``FrameResult.scale_observed``, large position covariance) until a scale aid (:meth:`add_velocity`,
    :meth:`add_fixation_point`) was used: the rays alone carry no scale on straight and constant-curvature
    motion (:mod:`.observability`), and too little on our other sequences to be trusted (docs/results.md, "Scale").
    ``scale_from_rotation`` restores the papers' assumption (observed after ``scale_min_rotation_deg`` of
    rotation).
    """

    GAP_TOLERANCE_S = 1e-6

    def __init__(self, rig: Rig, config: EstimatorConfig | None = None) -> None:
        self.rig = rig
        self.config = config or EstimatorConfig()
        self.solver = TwoFrameSolver(self.config.solver)
        self.reset()

    def reset(self) -> None:
        n = max(self.config.window, 2)
        self._window: deque[_Slot] = deque(maxlen=n)
        self._index = -1
        self._key_stamp: float | None = None
        self._key_pose = Pose.identity()
        self._key_pose_raw = Pose.identity()
        self._key_cov = np.zeros((6, 6))
        self._latest: _Latest | None = None
        self._velocity: tuple[np.ndarray, np.ndarray] | None = None  # [rvec, t] per second: refined, raw
        self._key_blind: _Blind | None = None   # the keyframe was reached by a blind (predicted) step
        self._speed = SpeedSamples()
        self._rotation_seen = 0.0          # rad of rig rotation between keyframes so far
        self._aids: set[str] = set()       # scale aids that have been used
        cfg = self.config
        self._speed_prior = ConstantSpeed(cfg.speed_nominal) if cfg.constant_speed else None
        # the speed was just measured: (factor that makes the path so far metric, key positions refined and raw
        # then); the path up to them was built at the nominal speed and is rescaled at the next keyframe, once
        self._pending_prefix: tuple[float, np.ndarray, np.ndarray] | None = None
        self._prefix_scale_out = 1.0        # reported with the next result
        # with the constant-speed prior, a vergence point fixes the scale (:mod:`.scale_anchor`); recent frames are kept
        # (bounded) because the measurement arrives after the frame it was made at
        self._anchor: ScaleAnchor | None = None
        self._anchors_used = 0              # vergence measurements that have calibrated the speed
        self._recent: deque[tuple[float, Pose, dict[str, Fixation | None]]] = deque(maxlen=ANCHOR_HISTORY)
        self._anchor_note = ''
        self._scale_measured: tuple[float, float] | None = None   # (stamp, relative std) of the newest measurement

    # ------------------------------------------------------------------------------------ scale aids
    def add_velocity(self, stamp: float, v_rig: np.ndarray, cov_rig: np.ndarray) -> None:
        """External speed source: velocity of the rig origin (m/s) in the rig frame at ``stamp`` with its
        3x3 covariance. Raises ValueError on non-finite values or a stamp not after the previous one."""
        v, cov = checked_measurement(stamp, v_rig, cov_rig, 'velocity sample')
        self._speed.add(float(stamp), v, cov)

    def add_fixation_point(self, stamp: float, side: str, point_rig: np.ndarray, cov_rig: np.ndarray) -> None:
        """Vergence aid: camera ``side``'s fixation point was at ``point_rig`` (rig frame at ``stamp``, m)
        with covariance ``cov_rig``. With the constant-speed prior every measurement is used, one at a time: it is
        followed while its camera keeps fixating the point and then re-measures the speed (the first one also
        makes the path so far metric). Without the prior it is not used (noted in :meth:`scale_note`)."""
        if side not in SIDES:
            raise ValueError(f'side must be one of {SIDES}, got {side!r}')
        point, cov = checked_measurement(stamp, point_rig, cov_rig, 'fixation point')
        if self._speed_prior is not None:
            self._start_anchor(float(stamp), side, point, cov)
        else:
            self._anchor_note = 'vergence measurement ignored: the papers\' method has no use for it'

    def _start_anchor(self, stamp: float, side: str, point: np.ndarray, cov: np.ndarray) -> None:
        """Constant-speed prior: the vergence point becomes a scale anchor, fed with the frames since its stamp."""
        if self._speed_prior is None or self._anchor is not None:
            self._anchor_note = 'vergence measurement ignored: the previous one is still being followed'
            return
        anchor = ScaleAnchor(stamp, side, point, cov, self.rig.center(side), self.config.solver.sigma)
        recent = list(self._recent)
        if recent and stamp < recent[0][0] - self.GAP_TOLERANCE_S:
            self._anchor_note = f'vergence measurement at {stamp:.3f} s is older than the frames kept: ignored'
            return
        self._anchor = anchor
        for f_stamp, pose, fix in recent:
            self._feed_anchor(f_stamp, pose, fix)

    def _remember(self, stamp: float, pose: Pose, fix: dict[str, Fixation | None]) -> None:
        """Constant-speed prior: keep a placed frame for a vergence measurement still to come, and feed the
        scale anchor with it."""
        if self._speed_prior is not None:
            self._recent.append((stamp, pose, fix))
            self._feed_anchor(stamp, pose, fix)

    def _feed_anchor(self, stamp: float, pose: Pose, fix: dict[str, Fixation | None]) -> None:
        """One placed frame for the scale anchor; calibrates the speed once the fit has settled."""
        a = self._anchor
        if a is None or self._speed_prior is None:
            return
        tol = self.GAP_TOLERANCE_S
        f = fix.get(a.side)
        if a.base is None:
            if abs(stamp - a.stamp) <= tol and f is not None:
                a.start(pose, f[1])
            elif stamp > a.stamp - tol:
                self._anchor, self._anchor_note = None, (f'vergence measurement at {a.stamp:.3f} s matches no frame '
                                                         f'with a {a.side} fixation: ignored')
            return
        if stamp <= a.stamp + tol:
            return
        a.add(stamp, pose, f[1] if f is not None else None, f[0] if f is not None else None)
        fit = a.settled()
        if fit is not None:
            first = not self._speed_prior.measured
            self._speed_prior.calibrate(fit.speed_k, fit.rel_std)
            self._scale_measured = (stamp, fit.rel_std)
            self._aids.add('the vergence step')
            self._anchors_used += 1
            if first:      # the path so far was drawn at the nominal speed: make it metric once
                self._pending_prefix = (fit.position_k, self._key_pose.t.copy(), self._key_pose_raw.t.copy())
            self._anchor = None
            done = f'path so far x{fit.position_k:.3f}' if first else 'speed re-measured'
            self._anchor_note = (f'vergence {self._anchors_used}: speed x{fit.speed_k:.3f} (std '
                                 f'{fit.rel_std * 100:.0f} %), {done}, from {len(a.views)} frames')
        elif a.ended:
            self._anchor, self._anchor_note = None, (f'vergence: the {a.side} camera left the point after '
                                                     f'{len(a.views)} frames, before the scale settled')

    @property
    def scale_measurement(self) -> tuple[float, float] | None:
        """(stamp, relative std) of the newest scale measurement (a settled vergence anchor), None before one.
        A speed source measures the scale at every step, so with one this stays None and nothing is requested."""
        return self._scale_measured

    @property
    def speed_source_used(self) -> bool:
        """Whether an external speed source has set step lengths (it measures the scale at every step)."""
        return 'the speed source' in self._aids

    @property
    def scale_observed(self) -> bool:
        if self._aids:
            return True
        if self._speed_prior is not None:
            return False                # every step has the nominal speed: turns do not change that
        return self.config.scale_from_rotation and self._turned

    @property
    def _turned(self) -> bool:
        return self._rotation_seen >= math.radians(self.config.scale_min_rotation_deg)

    def scale_note(self) -> str:
        if self._aids:
            note = 'scale from ' + ' and '.join(sorted(self._aids))
            return f'{note} ({self._anchor_note})' if self._anchor_note else note
        need = self.config.scale_min_rotation_deg
        seen = math.degrees(self._rotation_seen)
        if self._speed_prior is not None:
            note = (f'scale unobserved: every step at the nominal {self._speed_prior.nominal:g} m/s '
                    '(constant-speed prior)')
            return f'{note}; {self._anchor_note}' if self._anchor_note else note
        if self.config.scale_from_rotation:
            if seen >= need:
                return f'scale observed: {seen:.0f} deg of rotation seen (scale_from_rotation)'
            return f'scale unobserved: {seen:.1f} of {need:.0f} deg rotation seen, no scale aid'
        return (f'scale unobserved: no scale aid ({seen:.0f} deg of rotation seen; the lever arm carries no scale on '
                'straight and constant-curvature motion and too little elsewhere to trust)')

    @property
    def last_stamp(self) -> float | None:
        """Stamp of the last frame taken (None after a reset)."""
        return self._latest.stamp if self._latest is not None else self._key_stamp

    def _ba_problem(self, obs: FrameObservation) -> tuple[BAProblem, bool]:
        """Terms for each camera over its keyframe window (never across a re-selection); and whether
        any camera has the full n-frame window (the papers wait for it before adjusting)."""
        n = self.config.window
        slots = list(self._window)
        terms: list[BATerm] = []
        full = False
        # prefixes[k] = motion from keyframe k to the newest keyframe
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

    def _length_jump(self, t: np.ndarray, dt: float, held: bool) -> str:
        """Why a step of translation ``t`` over ``dt`` is a jump ('' if it is not). ``held``: the length was solved
        with the constant-speed prior, so it is the prior's (a gauge while the scale is unobserved): only a
        length far off it is a jump, not one beyond the metric limits."""
        cfg = self.config
        n = float(np.linalg.norm(t))
        if held and self._speed_prior is not None:
            length, std = self._speed_prior.prior(dt)
            far = abs(n - length) > 5 * std
            return f'jump: |T| = {n:.3f} m, the constant-speed prior says {length:.3f}' if far else ''
        if n > cfg.max_step_translation:
            return f'jump: |T| = {n:.3f} m > {cfg.max_step_translation}'
        if dt > 0 and n > cfg.max_speed * dt:
            return f'jump: {n / dt:.2f} m/s > {cfg.max_speed} m/s'
        return ''

    def _accept(self, res: TwoFrameResult, dt: float, held: bool) -> tuple[bool, str]:
        cfg = self.config
        if not res.status.usable:
            return False, f'two-frame {res.status.value}: {res.message}'
        if not res.pose.is_finite():
            return False, 'non-finite solution'
        jump = self._length_jump(res.pose.t, dt, held)
        if jump:
            return False, jump
        if rotation_angle(res.pose.R) > cfg.max_step_rotation:
            return False, f'jump: rotation {np.degrees(rotation_angle(res.pose.R)):.1f} deg'
        if float(np.max(res.translation_std)) > cfg.reject_translation_std:
            return False, 'translation covariance too large'
        return True, ''

    def _reject(self, obs: FrameObservation, why: str) -> FrameResult:
        """A frame that cannot be placed: reported, state unchanged."""
        latest = self._latest
        pose, pose_raw, cov = ((latest.pose, latest.pose_raw, latest.pose_cov) if latest is not None
                               else (self._key_pose, self._key_pose_raw, self._key_cov))
        return FrameResult.rejected(self._index, obs.stamp, pose, pose_raw, why, cov)

    def update(self, obs: FrameObservation) -> FrameResult:
        """Process one frame. Never raises on bad data; bad steps are flagged and predicted.

        A frame whose stamp is not after the last one, or whose flow starts at a frame the estimator
        cannot place, is rejected without changing the state. When ``obs.prev_stamp`` is later than the
        last frame seen (frames were missed), the gap is bridged by a constant-velocity prediction and
        the fixation window restarts, since the missed frames' fixations are unknown."""
        tol = self.GAP_TOLERANCE_S
        last = self.last_stamp
        if last is not None and not obs.stamp > last:
            return self._reject(obs, f'stamp {obs.stamp:.6f} not after the last frame {last:.6f}: ignored')
        gap = ''
        if last is not None:
            ref = obs.prev_stamp if obs.prev_stamp is not None else last
            if self._latest is not None and abs(ref - self._latest.stamp) <= tol:
                self._promote()
            elif abs(ref - self._key_stamp) <= tol:
                pass                                     # flow from the current keyframe again
            elif last + tol < ref < obs.stamp:
                if self._latest is not None:
                    self._promote()
                gap = self._bridge(ref)
            else:
                return self._reject(obs, f'flow starts at {ref:.6f}, which is neither the keyframe '
                                         f'({self._key_stamp:.6f}) nor a frame after it: ignored')
        self._index += 1
        fix = fixations_of(obs)
        if self._key_stamp is None:
            self._key_stamp = obs.stamp
            self._window.append(_Slot(fix, Pose.identity()))
            self._remember(obs.stamp, self._key_pose, fix)
            return FrameResult(self._index, obs.stamp, StepStatus.INIT, self._key_pose, self._key_pose_raw,
                               Pose.identity(), Pose.identity(), np.zeros((6, 6)), self._key_cov.copy(),
                               'first frame', scale_observed=self.scale_observed, scale_note=self.scale_note())
        dt = obs.stamp - self._key_stamp
        pairs = step_pairs(self.rig, self._window[-1].fixation, obs, self.config.fixation_weight,
                           self.config.joint_weighting)
        prediction = self._predict(dt)
        start = self._latest.motion_raw if self._latest is not None else (prediction[1] if prediction else None)
        cfg = self.config
        rotation = self._step_rotation(pairs, prediction) if self._speed.stamps else None   # (no SVD without one)
        speed = self._speed.translation(self._key_stamp, obs.stamp, rotation)
        if speed is not None:
            sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(speed[1]))), 1e-12))
            tf = self.solver.solve(pairs, initial=start, prior_t=speed[0], prior_sigma_t=sigma)
        elif self._speed_prior is not None:
            tf = self.solver.solve(pairs, initial=start, prior_length=self._speed_prior.prior(dt))
        elif cfg.velocity_prior and prediction is not None:
            t_pred = prediction[1].t
            sigma = max(cfg.prior_sigma_min, cfg.prior_sigma_rel * float(np.linalg.norm(t_pred)))
            tf = self.solver.solve(pairs, initial=start, prior_t=t_pred, prior_sigma_t=sigma)
        else:
            tf = self.solver.solve(pairs, initial=start)
        held = speed is None and self._speed_prior is not None     # the length is the constant-speed prior's
        accepted, why = self._accept(tf, dt, held)
        ba: BAResult | None = None
        if accepted:
            motion = motion_raw = tf.pose
            cov = tf.covariance
            status = tf.status
            message = tf.message
            # the local BA has no term for a speed source's translation, so with one it would let the length
            # float again (42 cm mean against 1.2 cm without it on the simulated loop): the two-frame solve stands
            if self.config.window >= 3 and obs.keyframe is not False and speed is None:
                problem, full = self._ba_problem(obs)
                if full and len(problem):
                    ba = refine_latest(problem, tf.pose, self.config.mode, pairs, self.config.solver.sigma,
                                       backend=self.config.solver.backend)
                    refined = ba.pose
                    if (not self._length_jump(refined.t, dt, held)
                            and rotation_angle(refined.R) <= self.config.max_step_rotation):
                        motion = refined
                    else:
                        message += '; BA result rejected as a jump'
            self._velocity = (np.concatenate([motion.rvec(), motion.t]) / dt,
                              np.concatenate([motion_raw.rvec(), motion_raw.t]) / dt)
        elif prediction is not None:
            motion, motion_raw = prediction
            cov = np.diag([1e-4] * 3 + [max(1e-2, float(np.sum(motion.t**2)))] * 3)
            status, message = StepStatus.PREDICTED, why + '; constant-velocity prediction'
        else:
            motion = motion_raw = Pose.identity()
            cov = np.diag([1e-2] * 3 + [VAR_MAX] * 3)
            status = StepStatus(tf.status if not tf.status.usable else StepStatus.REJECTED)
            message = why + '; held'
        corrected = self._rebridge() if accepted else None
        pose_cov = self._propagate(self._key_pose, self._key_cov, motion, cov)
        pose = (self._key_pose @ motion).normalized()
        pose_raw = (self._key_pose_raw @ motion_raw).normalized()
        blind = (_Blind(self._key_pose, self._key_pose_raw, dt, self._velocity)
                 if status == StepStatus.PREDICTED and self._velocity is not None else None)
        self._latest = _Latest(obs.stamp, fix, motion, motion_raw, pose, pose_raw, pose_cov, cov, blind=blind)
        if speed is not None:
            self._aids.add('the speed source')
        key_stamp = self._key_stamp
        if obs.keyframe:
            self._promote()
            pose, motion = self._key_pose, self._window[-1].step.normalized()
        if gap:
            message = f'{gap}; {message}' if message else gap
        self._remember(obs.stamp, pose, fix)
        observed = self.scale_observed
        if not observed:      # the position is known only up to an unobserved scale: say so
            pose_cov = pose_cov.copy()
            pose_cov[3:, 3:] += np.eye(3) * (1.0 + float(np.linalg.norm(pose.t))) ** 2
        prefix_scale, self._prefix_scale_out = self._prefix_scale_out, 1.0
        return FrameResult(self._index, obs.stamp, status, pose, pose_raw, motion, motion_raw, cov,
                           pose_cov.copy(), message, tf, ba, key_stamp, scale_observed=observed,
                           scale_note=self.scale_note(), prefix_scale=prefix_scale, corrected=corrected)

    def _rebridge(self) -> tuple[float, Pose, Pose] | None:
        """The keyframe was reached by a blind step, predicted from the rates before it; now that the step out of
        it is solved (its rates are ``_velocity``), give it the mean of the rates before and after (a turn that
        ends inside the blind step is then half-counted, not continued for the whole step), and move the
        keyframe accordingly."""
        b, self._key_blind = self._key_blind, None
        if b is None or self._key_stamp is None or self._velocity is None:
            return None
        step, step_raw = (_motion_at(0.5 * (before + after), b.dt)
                          for before, after in zip(b.rate, self._velocity, strict=True))
        self._key_pose = (b.start @ step).normalized()
        self._key_pose_raw = (b.start_raw @ step_raw).normalized()
        self._window[-1].step = step
        return self._key_stamp, self._key_pose, self._key_pose_raw

    def _promote(self) -> None:
        """The newest frame becomes the keyframe later flow starts from."""
        f = self._latest
        assert f is not None
        prev_pose = self._key_pose
        pose = f.pose
        self._rotation_seen += rotation_angle(prev_pose.R.T @ pose.R)
        self._window.append(_Slot(f.fixation, prev_pose.inverse() @ pose))
        self._speed.forget_before(self._key_stamp)     # later steps start at this keyframe or after
        pose_raw = f.pose_raw
        rescaled = self._pending_prefix is not None
        if rescaled:
            pose, pose_raw = self._rescale_prefix(pose, pose_raw)
        self._key_stamp, self._key_pose, self._key_pose_raw, self._key_cov = f.stamp, pose, pose_raw, f.pose_cov
        self._key_blind = None if rescaled else f.blind
        self._latest = None

    def _rescale_prefix(self, pose: Pose, pose_raw: Pose) -> tuple[Pose, Pose]:
        """The speed was measured: the path up to the measurement was built at the nominal speed, so stretch it
        to the measured one (once; later steps are made at the measured speed)."""
        assert self._pending_prefix is not None
        k, anchor, anchor_raw = self._pending_prefix
        self._pending_prefix = None
        self._prefix_scale_out = k
        return Pose(pose.R, pose.t + (k - 1.0) * anchor), Pose(pose_raw.R, pose_raw.t + (k - 1.0) * anchor_raw)

    @staticmethod
    def _step_rotation(pairs: RayPairs, prediction: tuple[Pose, Pose] | None) -> np.ndarray | None:
        """The step's rotation vector before the solve, to put a speed source's velocities into the keyframe's
        frame: the rotation-only fit of the step's rays (the translation is small against the depths), else
        the constant-velocity prediction."""
        if len(pairs) >= MIN_ROTATION_PAIRS:
            return Pose(kabsch_rotation(pairs.a, pairs.b), np.zeros(3)).rvec()
        return prediction[0].rvec() if prediction is not None else None

    def _predict(self, dt: float) -> tuple[Pose, Pose] | None:
        """Constant-velocity motion over ``dt`` (refined, raw), or None before the first solved step."""
        if self._velocity is None:
            return None
        v, v_raw = self._velocity
        return _motion_at(v, dt), _motion_at(v_raw, dt)

    def _bridge(self, ref: float) -> str:
        """Advance the keyframe over frames that never arrived (keyframe -> ``ref``) at constant velocity."""
        assert self._key_stamp is not None
        dt = ref - self._key_stamp
        prediction = self._predict(dt)
        if prediction is not None:
            step, step_raw = prediction
            cov = np.diag([1e-4] * 3 + [max(1e-2, float(np.sum(step.t**2)))] * 3)
        else:
            step = step_raw = Pose.identity()
            cov = np.diag([1e-2] * 3 + [VAR_MAX] * 3)
        self._key_cov = self._propagate(self._key_pose, self._key_cov, step, cov)
        self._key_pose = (self._key_pose @ step).normalized()
        self._key_pose_raw = (self._key_pose_raw @ step_raw).normalized()
        self._key_stamp, self._key_blind = ref, None
        # the missed frames' fixations are unknown: no fixation pair or BA term may span the gap
        self._window.append(_Slot({side: None for side in SIDES}, step))
        return f'{dt:.3f} s of missing frames bridged by a constant-velocity prediction'

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
