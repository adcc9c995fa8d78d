"""Options of the back ends: :class:`EstimatorConfig` (both) and :class:`SmootherConfig` (the metric one)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from fixego_ros.estimation.covariance import VAR_MAX
from fixego_ros.estimation.frames import JointWeighting
from fixego_ros.estimation.local_ba import MODES
from fixego_ros.estimation.twoframe import SolverConfig


@dataclass(frozen=True)
class SmootherConfig:
    """Options of the smoother (estimator_node's ``smoother_*`` parameters; pixels in pixels here)."""

    lag_s: float = 3.0                  # variables older than this are marginalised
    pixel_sigma_px: float = 1.0
    huber_k: float = 1.345              # projection residuals: Huber threshold in sigmas
    mount_rotation_sigma: float = 4e-4  # rad: how far a camera may sit from its pan/tilt readings
    twist_rotation_sigma: float = 0.1   # constant-twist prior, rad/s per step
    twist_translation_sigma: float = 0.05   # m/s per step, until a scale aid is used
    twist_speed_sigma: float = 0.3      # after: change of the velocity per step over the speed
    gate_px: float = 8.0                # an observation this far from its landmark (after resection) is left out
    min_views: int = 3                  # a landmark enters once seen this often ...
    min_parallax_deg: float = 0.5       # ... with rays this far apart (a fixation point enters at a far guess)
    far_guess_m: float = 4.0            # depth of a fixation landmark placed without parallax
    max_range_m: float = 30.0           # a track triangulated farther than this waits for more parallax ...
    patient_views: int = 6              # ... unless seen this often (then it enters as it is, or at the far guess)
    landmark_prior_m: float = 10.0      # weak prior on a new landmark (keeps a barely seen one determined)
    step_floor_px: float = 3.0          # two-frame step rotation sigma floor (px of rotation)
    step_cauchy_k: float = 1.0          # two-frame step factors: Cauchy threshold in sigmas
    nominal_speed: float = 0.5          # m/s: the two-frame steps' length gauge until a scale aid measures it
    iterations: int = 1                 # extra Gauss-Newton passes per frame (relinearisation)
    min_resection: int = 6              # observations of existing landmarks needed to place a frame by them
    forward_sigma_deg: float = 5.0      # motion model: the rig moves along its forward axis, this std (0 = off)
    speed_scale_sigma: float = 0.05     # prior std of the speed source's scale (its wheel radius error; 0 = exact)

    def __post_init__(self) -> None:
        positive = ('lag_s', 'pixel_sigma_px', 'huber_k', 'mount_rotation_sigma', 'twist_rotation_sigma',
                    'twist_translation_sigma', 'twist_speed_sigma', 'gate_px', 'min_parallax_deg', 'far_guess_m',
                    'max_range_m',
                    'landmark_prior_m', 'step_floor_px', 'step_cauchy_k', 'nominal_speed')
        for name in positive:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f'{name} must be finite and > 0, got {v}')
        if not (math.isfinite(self.forward_sigma_deg) and 0.0 <= self.forward_sigma_deg < 90.0):
            raise ValueError(f'forward_sigma_deg must be in [0, 90), got {self.forward_sigma_deg}')
        if not (math.isfinite(self.speed_scale_sigma) and 0.0 <= self.speed_scale_sigma <= 1.0):
            raise ValueError(f'speed_scale_sigma must be in [0, 1], got {self.speed_scale_sigma}')
        if self.min_views < 2 or self.patient_views < self.min_views or self.iterations < 0 or self.min_resection < 3:
            raise ValueError('min_views must be >= 2, patient_views >= min_views, iterations >= 0, min_resection >= 3')



REFINEMENTS = ('smoother', 'local')


@dataclass(frozen=True)
class EstimatorConfig:
    """Options of the estimator. The defaults are estimator_node's (``pipeline.params``, a test keeps them equal);
    the papers' method as ``fixego paper-sim`` runs it is :func:`papers_config`."""

    window: int = 3                  # n: frames in the local BA (3..10); 0 or 1 disables it
    mode: str = 'joint'              # 'paper' (BA cost alone, Powell) or 'joint'
    fixation_weight: float = 1.0     # weight of the fixation constraints relative to flow points
    # rad: a camera whose stated pan/tilt 1-sigma exceeds this counts less in the two-frame step and the smoother's
    # resection (:class:`~fixego_ros.estimation.frames.JointWeighting`); 0 = every camera counts fully
    joint_sigma_nominal: float = math.radians(0.1)
    max_step_translation: float = 0.5  # m; larger steps are rejected as jumps
    max_step_rotation: float = math.radians(20.0)  # rad
    max_speed: float = 1.5             # m/s; a step implying a faster rig is rejected as a jump
    reject_translation_std: float = VAR_MAX  # m; steps less certain than this are rejected
    # weak constant-velocity prior on each step's T (off = the papers' method): sigma = max(min, rel * |T_pred|)
    velocity_prior: bool = False
    prior_sigma_rel: float = 0.5
    prior_sigma_min: float = 0.01     # m
    solver: SolverConfig = field(default_factory=SolverConfig)
    # 'smoother': the metric back end (:mod:`.smoother`, a fixed-lag factor graph over poses and landmarks);
    # 'local': the papers' method, the local BA of the latest step over ``window`` frames (:mod:`.estimator`)
    refinement: str = 'smoother'
    smoother: SmootherConfig = field(default_factory=SmootherConfig)
    # 'local': with ``scale_from_rotation`` the metric scale counts as observed once the rig has turned this much
    # (the papers' assumption; see :mod:`.observability` for when the lever arm carries no scale at all: straight
    # and constant-curvature motion)
    scale_min_rotation_deg: float = 15.0
    scale_from_rotation: bool = False
    # 'local' only: constant-speed prior (:mod:`.constant_speed`): every step at one speed, nominal until the
    # vergence step (:meth:`Estimator.add_fixation_point`) measures it; off = the papers' free two-frame lengths
    constant_speed: bool = True
    speed_nominal: float = 0.5        # m/s

    def __post_init__(self) -> None:
        if self.refinement not in REFINEMENTS:
            raise ValueError(f'refinement must be one of {REFINEMENTS}, got {self.refinement!r}')
        if not (math.isfinite(self.scale_min_rotation_deg) and self.scale_min_rotation_deg >= 0):
            raise ValueError(f'scale_min_rotation_deg must be finite and >= 0, got {self.scale_min_rotation_deg}')
        if self.mode not in MODES:
            raise ValueError(f'mode must be one of {MODES}, got {self.mode!r}')
        if self.window not in (0, 1) and not 3 <= self.window <= 10:
            raise ValueError(f'window must be 3..10 (or 0 to disable the local BA), got {self.window}')
        if not (math.isfinite(self.joint_sigma_nominal) and self.joint_sigma_nominal >= 0.0):
            raise ValueError(f'joint_sigma_nominal must be finite and >= 0, got {self.joint_sigma_nominal}')

    @property
    def joint_weighting(self) -> JointWeighting:
        """How the two-frame step weighs each camera by its pan/tilt reading's stated sigma."""
        return JointWeighting(self.solver.sigma, self.joint_sigma_nominal)


def papers_solver(**overrides: Any) -> SolverConfig:
    """The two-frame solve of the papers' experiments: plain least squares (no robust loss), up to 60
    evaluations, no stationary detection (the simulated rig always moves)."""
    return SolverConfig(**{'loss': 'linear', 'max_nfev': 60, 'min_parallax': 1e-7, **overrides})


def papers_config(**overrides: Any) -> EstimatorConfig:
    """The papers' method as ``fixego paper-sim`` and the core benchmark run it: the local BA in 'paper' mode
    (Powell on the BA cost alone), free two-frame lengths (no constant-speed prior), no speed limit and loose
    jump bounds (1 m, 0.35 rad), and :func:`papers_solver`. ``overrides`` replace any field."""
    values: dict[str, Any] = {'mode': 'paper', 'max_step_translation': 1.0, 'max_step_rotation': 0.35,
                              'max_speed': math.inf, 'constant_speed': False, 'solver': papers_solver()}
    return EstimatorConfig(**{**values, **overrides})
