"""The parameters of every node, each specified once, shared by the nodes and ``fixego replay``.

A :class:`ParamSpec` holds a parameter's name, default, type, allowed range (or set), description and
whether it may change at run time. Everything else is generated from it: the nodes' ROS declarations
(descriptor with range and constraints, :mod:`fixego_ros.nodes.common`), the checks of ``-p`` overrides,
parameter files and ``ros2 param set``, and ``config/<node>.yaml``
(``python -m fixego_ros.pipeline.params --write-config config/``). The builders turn any ``get(name)``
callable (a node's parameter getter, or :func:`params_getter` over a YAML file) into the core's config
objects, so a replay runs with exactly what the live nodes would use. ROS-free.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import re
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import yaml

from fixego_ros.estimation.config import REFINEMENTS, EstimatorConfig, SmootherConfig
from fixego_ros.estimation.local_ba import MODES
from fixego_ros.estimation.twoframe import BACKENDS, LOSSES, MIN_STAND_PAIRS, SolverConfig
from fixego_ros.geometry.rig import SIDES, Rig
from fixego_ros.pipeline.frontend import KeyframePolicy
from fixego_ros.pipeline.odometry import SPEED_PARAMS as _SPEED_TEXTS
from fixego_ros.pipeline.sync import SyncParams
from fixego_ros.sim.trajectories import NAMES as TRAJECTORIES
from fixego_ros.sim.trajectories import REST_RANGE
from fixego_ros.tracking.fixation import FixationParams
from fixego_ros.tracking.flow import PRESETS, FlowParams
from fixego_ros.tracking.joint_prediction import MODES as JOINT_MODES
from fixego_ros.visca.driver import MAX_TIMEOUT_S

Value = bool | int | float | str | list[str]
Getter = Callable[[str], object]


_NUMBER = re.compile(r'[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+')


class ParamsError(ValueError):
    """A parameter value, file or override that does not fit its specification; the message is one line
    naming the parameter, the value and what is allowed."""


def _num_text(x: float) -> str:
    return f'{x:g}'


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter. ``type`` is bool, int, float, str or list (a string array, ``default`` None =
    unset). Numbers must lie in [min, max] (``min_open``/``max_open`` make a bound exclusive; None = no
    bound), or be one of ``also`` (special values such as 0 = off); floats must be finite. Strings must be
    one of ``choices`` when given. ``read_only``: taken at start only (structural); otherwise the node
    applies a change made at run time."""

    name: str
    default: Value | None
    description: str
    type: type
    min: float | None = None
    max: float | None = None
    min_open: bool = False
    max_open: bool = False
    choices: tuple[str, ...] = ()
    also: tuple[float, ...] = ()
    read_only: bool = True

    def __post_init__(self) -> None:
        if self.default is not None:
            self.check(self.default)        # a spec whose own default is refused is a bug: fail at import

    # ------------------------------------------------------------------------------------------ text
    def allowed(self) -> str:
        """What the value may be, in words (error messages, descriptor constraints, config comments)."""
        if self.type is bool:
            return 'true or false'
        if self.type is list:
            return 'list of strings'
        if self.type is str:
            return 'one of ' + ', '.join(repr(c) for c in self.choices) if self.choices else 'any string'
        kind = 'finite float' if self.type is float else 'integer'
        lo, hi = self.min, self.max
        if lo is not None and hi is not None:
            text = (f'{kind} in {"(" if self.min_open else "["}{_num_text(lo)}, {_num_text(hi)}'
                    f'{")" if self.max_open else "]"}')
        elif lo is not None:
            text = f'{kind} {">" if self.min_open else ">="} {_num_text(lo)}'
        elif hi is not None:
            text = f'{kind} {"<" if self.max_open else "<="} {_num_text(hi)}'
        else:
            text = kind
        if self.also:
            text += ', or ' + ' or '.join(_num_text(a) for a in self.also)
        return text

    def hull(self) -> tuple[float | None, float | None]:
        """Smallest closed interval holding every allowed number (for the ROS range descriptor)."""
        lo = None if self.min is None else min([self.min, *self.also])
        hi = None if self.max is None else max([self.max, *self.also])
        return lo, hi

    # ------------------------------------------------------------------------------------------ check
    def _error(self, value: object, problem: str) -> ParamsError:
        return ParamsError(f'parameter {self.name}: {value!r} {problem} (allowed: {self.allowed()})')

    def check(self, value: object) -> Value:
        """``value`` as this parameter's type (an int for a float parameter becomes a float), or
        :class:`ParamsError` naming the parameter, the value and the allowed range."""
        t = self.type
        if t is bool:
            if not isinstance(value, bool):
                raise self._error(value, 'has the wrong type')
            return value
        if t is str:
            if isinstance(value, bool) and {'true', 'false'} <= set(self.choices):
                value = 'true' if value else 'false'      # `-p publish_tf:=false` arrives as a bool
            if not isinstance(value, str):
                raise self._error(value, 'has the wrong type')
            if self.choices and value not in self.choices:
                close = difflib.get_close_matches(value, self.choices, n=1)
                raise self._error(value, 'is not allowed' + (f" (did you mean '{close[0]}'?)" if close else ''))
            return value
        if t is list:
            if not isinstance(value, (list, tuple)) or not all(isinstance(x, str) for x in value):
                raise self._error(value, 'has the wrong type')
            return list(value)
        if isinstance(value, str) and _NUMBER.fullmatch(value.strip()):
            value = float(value)       # YAML 1.1 reads 1e6 (no dot) as a string; ROS's own parser takes it as a number
            if t is int and value.is_integer():
                value = int(value)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or (t is int and isinstance(value, float)):
            raise self._error(value, 'has the wrong type')
        v: int | float = float(value) if t is float else int(value)
        if not math.isfinite(v):
            raise self._error(value, 'is not finite')
        if v in self.also:
            return v
        lo, hi = self.min, self.max
        if ((lo is not None and (v < lo or (self.min_open and v == lo)))
                or (hi is not None and (v > hi or (self.max_open and v == hi)))):
            raise self._error(value, 'is out of range')
        return v


Table = dict[str, ParamSpec]


def _num(name: str, default: float, description: str, *, ge: float | None = None, gt: float | None = None,
         le: float | None = None, lt: float | None = None, also: tuple[float, ...] = (),
         live: bool = False) -> ParamSpec:
    """A number; int or float after the default. Integer bounds are made inclusive."""
    t = int if isinstance(default, int) and not isinstance(default, bool) else float
    lo, lo_open = (gt, True) if gt is not None else (ge, False)
    hi, hi_open = (lt, True) if lt is not None else (le, False)
    if t is int:
        if lo is not None and lo_open:
            lo, lo_open = lo + 1, False
        if hi is not None and hi_open:
            hi, hi_open = hi - 1, False
    return ParamSpec(name, default, description, t, lo, hi, lo_open, hi_open, also=also, read_only=not live)


def _str(name: str, default: str, description: str, *, choices: tuple[str, ...] = (),
         live: bool = False) -> ParamSpec:
    return ParamSpec(name, default, description, str, choices=tuple(choices), read_only=not live)


def _bool(name: str, default: bool, description: str, *, live: bool = False) -> ParamSpec:
    return ParamSpec(name, default, description, bool, read_only=not live)


def _strings(name: str, description: str) -> ParamSpec:
    """A string array, unset by default."""
    return ParamSpec(name, None, description, list)


def _table(*specs: ParamSpec | Table) -> Table:
    out: Table = {}
    for s in specs:
        for spec in (s.values() if isinstance(s, dict) else (s,)):
            if spec.name in out:
                raise ValueError(f'parameter {spec.name} specified twice')
            out[spec.name] = spec
    return out


DIAGNOSTICS_PERIOD = ('diagnostics publishing period (s)', {'ge': 0.05, 'le': 3600.0})
RIG_FILE = 'rig calibration YAML (DESIGN.md §4); empty = the package config/rig.yaml'


def _diagnostics_period(live: bool = True) -> ParamSpec:
    return _num('diagnostics_period_s', 1.0, DIAGNOSTICS_PERIOD[0], live=live, **DIAGNOSTICS_PERIOD[1])


# camera_node: the fixation point tracker (read per frame, so they change at run time but the template size)
FIXATION_PARAMS: Table = _table(
    _num('search_radius_px', 60.0, 'fixation selection window radius around the centre', gt=0.0, live=True),
    _num('min_corner_score', 2e-4, 'minimum corner (min-eigenvalue) score of a fixation point', ge=0.0, live=True),
    _num('template_half_px', 10, 'half size of the NCC validity template', ge=1, le=100),
    _num('ncc_min', 0.7, 'template correlation below which the track counts as lost', ge=-1.0, le=1.0, live=True),
    _num('fb_max_px', 1.0, 'forward-backward LK error above which the track counts as lost', gt=0.0, live=True),
    _num('border_margin_px', 40.0, 're-select when the fixation comes this close to the image border', ge=0.0,
         live=True),
    _num('relocate_radius_px', 400.0, 'when LK loses the fixation point, search its template this far around the '
         'last pixel (an unambiguous match keeps the point and its id); 0 = off', ge=0.0, live=True),
)

# flow_node: synchronisation, flow tracking and keyframes (thresholds read per frame change at run time)
FLOW_PARAMS: Table = _table(
    _str('preset', 'full', "flow points: 'paper' (3 in the central 30x30 px), 'window' (all good corners in "
                             "the window), 'full' (whole image)", choices=PRESETS),
    _num('window_px', 100, 'side of the flow window centred on the fixation point (px)', ge=4, le=10000),
    _num('paper_region_px', 30, 'paper preset: side of the central region the points are drawn from (px)', ge=1,
         le=10000),
    _num('paper_points', 3, 'paper preset: points per camera', ge=1, le=1000),
    _num('max_corners', 80, 'window/full presets: most corners tracked per camera (the solve time grows with it)',
         ge=1, le=20000),
    _num('min_eig', 1e-3, 'Lucas-Kanade minimum-eigenvalue threshold (rejects untextured points)', ge=0.0,
         live=True),
    _num('fb_max_px', 0.5, 'forward-backward consistency bound (px)', gt=0.0, live=True),
    _num('lk_win', 21, 'Lucas-Kanade window (px)', ge=3, le=201),
    _num('lk_levels', 3, 'pyramid levels', ge=0, le=8),
    _num('ransac_px', 1.0, 'epipolar RANSAC inlier bound per camera, keyframe -> now (px; 0 = off)', ge=0.0,
         live=True),
    _num('register_period_s', 0.1, "each track's birth patch is registered at its tracked position about this "
         'often (s; 0 = every frame): a share of the tracks per frame, the longest unregistered first', ge=0.0,
         le=10.0, live=True),
    _num('keyframe_max_frames', 10, 'frames tracked from one keyframe at most (1 = consecutive frames, the papers)',
         ge=1, le=1000, live=True),
    _num('keyframe_min_parallax_px', 0.0, 'new keyframe once the rotation-compensated parallax reaches this '
                                          '(0 = off)', ge=0.0, live=True),
    _num('keyframe_min_tracked_fraction', 0.5, "new keyframe when fewer of the keyframe's points still track",
         ge=0.0, le=1.0, live=True),
    _num('keyframe_max_rotation_deg', 8.0, 'new keyframe once the rig rotation since the keyframe exceeds this '
                                           '(deg; 0 = off)', ge=0.0, le=180.0, live=True),
    _num('slop_s', 0.0, 'images of the two cameras closer than this form one frame (s); 0 = automatic: half the '
                        'median frame period measured from the image stamps, within [0.001, 0.05] s', ge=0.0, le=10.0,
         live=True),
    _num('max_wait_s', 0.25, 'bound on waiting for a partner image, joint state or fixation (s)', ge=0.0, le=60.0,
         live=True),
    _num('joint_extrapolation_s', 0.0, 'how far past the newest joint state an image may be (s); 0 = wait for one',
         ge=0.0, le=10.0, live=True),
)

# estimator_node: two-frame solve and local bundle adjustment (the step acceptance thresholds change at run time)
ESTIMATOR_PARAMS: Table = _table(
    _str('refinement', 'smoother', "'smoother': the metric back end, a fixed-lag factor graph over rig poses, camera "
                                   'poses and landmarks that uses the vergence measurements and a speed source '
                                   "(README \"Back end\"); 'local': the papers' method, the local BA of the latest "
                                   'step over `window` frames', choices=REFINEMENTS),
    _num('window', 3, 'n: frames in the local bundle adjustment (3..10; 0 disables it)', ge=3, le=10, also=(0, 1)),
    _str('mode', 'joint', "local BA: 'joint' (BA cost + the two-frame terms: well posed, the same answer on any "
                          "CPU) or 'paper' (BA cost alone, Powell, as in the papers: few terms against 6 unknowns, "
                          'so where it stops depends on rounding)', choices=MODES),
    _num('fixation_weight', 1.0, 'weight of the fixation constraints relative to one flow point', ge=0.0, le=1e6,
         live=True),
    _num('joint_sigma_nominal_deg', 0.1, 'a camera whose pan/tilt reading is less sure than this (the 1-sigma its '
                                         'camera node states in joint_states effort: a fast turn, its angle '
                                         'predicted) counts less in the two-frame step and the smoother\'s '
                                         'resection: the reading rotates every ray, so its variance adds to the '
                                         "rays' (deg; 0 = every camera counts fully)", ge=0.0, le=10.0),
    _num('stationary_parallax_px', 0.3, 'median rotation-compensated parallax (px) below which the rig is taken as '
                                        'standing still (T = 0): with no parallax the scale is pure noise. A step '
                                        f'with fewer than {MIN_STAND_PAIRS} ray pairs never stands (a handful is no '
                                        'evidence of rest)', ge=0.0),
    _num('stationary_camera_parallax_px', 0.1, 'with both cameras: standing still needs each camera\'s parallax, '
                                               'with a rotation of its own, below this (px; 0 = one rotation for both '
                                               'against stationary_parallax_px) ...', ge=0.0),
    _num('stationary_head_sigma_deg', 0.033, '... and the two rotations within 3 sqrt(2) of this (the heads\' '
                                             'independent reading error; EVI-D30: 1 unit = 0.114 deg, /sqrt(12))',
         ge=0.0),
    _num('pixel_sigma', 1.0, 'expected flow/fixation noise in pixels (sets the covariance scale)', gt=0.0),
    _str('loss', 'huber', 'robust loss of the two-frame solve: linear | huber | soft_l1 | cauchy | arctan',
         choices=LOSSES),
    _bool('velocity_prior', False, "weak constant-velocity prior on each step (keeps unobserved scale from "
                                   "wandering; the covariance stays the rays' own). false = the papers' method",
          live=True),
    _num('prior_sigma_rel', 0.5, 'prior std as a fraction of the predicted step length', gt=0.0, live=True),
    _num('prior_sigma_min', 0.01, 'prior std at least this (m)', gt=0.0, live=True),
    _num('max_nfev', 30, 'bound on function evaluations of one two-frame solve', ge=1, le=100000),
    _str('solver_backend', 'lm', "least squares of the two-frame solve and the least-squares BA modes: 'lm' (our "
                                 "compact Levenberg-Marquardt, ~3x faster) or 'scipy' "
                                 '(scipy.optimize.least_squares trf)', choices=BACKENDS),
    _num('max_step_translation', 0.5, 'm; a larger step is rejected as a jump and predicted instead', gt=0.0,
         live=True),
    _num('max_speed', 1.5, 'm/s; a step implying a faster rig is rejected as a jump and predicted instead', gt=0.0,
         live=True),
    _num('max_step_rotation_deg', 20.0, 'deg; a larger step rotation is rejected as a jump', gt=0.0, le=180.0,
         live=True),
    _num('reject_translation_std', 1e6, 'm; a step whose translation std exceeds this is rejected (1e6: never)',
         gt=0.0, live=True),
    _num('smoother_lag_s', 3.0, 'smoother: poses and landmarks older than this are marginalised (s); a vergence '
                                'measurement older than this when it arrives is not used', gt=0.0, le=60.0),
    _num('smoother_iterations', 1, 'smoother: extra relinearisations per frame (0 saves ~a quarter of the '
                                   'smoother\'s time but lost 3 of 9 test bags, docs/results.md "Stop 66")',
         ge=0, le=20),
    _num('smoother_gate_px', 8.0, 'smoother: an observation farther than this from its landmark (after the pose-only '
                                  'placement of the frame) is left out (px)', gt=0.0),
    _num('smoother_min_parallax_deg', 0.5, 'smoother: a track enters the graph once its rays span this angle', gt=0.0,
         lt=180.0),
    _num('smoother_twist_rotation_sigma', 0.1, 'smoother: constant-twist prior, change of the angular rate per frame '
                                               '(rad/s)', gt=0.0),
    _num('smoother_twist_translation_sigma', 0.05, 'smoother: constant-twist prior, change of the velocity per frame '
                                                   '(m/s) while the scale is unmeasured (holds the nominal speed)',
         gt=0.0),
    _num('smoother_twist_speed_sigma', 0.3, 'smoother: constant-twist prior once a scale aid is used, change of the '
                                            'velocity per frame as a fraction of the speed (scale-free)', gt=0.0),
    _num('smoother_step_floor_px', 3.0, 'smoother: the two-frame step factors claim no better rotation than this '
                                        '(px)', gt=0.0),
    _num('smoother_step_cauchy', 1.0, 'smoother: Cauchy threshold of the two-frame step factors (sigmas)', gt=0.0),
    _num('smoother_mount_rotation_sigma', 4e-4, 'smoother: how far a camera may sit from its pan/tilt readings (rad)',
         gt=0.0),
    _num('smoother_forward_sigma_deg', 5.0, 'smoother: motion model, the rig moves along its forward axis (rig z) '
                                            'within this std (deg, Cauchy-robust); 0 = off (a rig that moves sideways)',
         ge=0.0, lt=90.0),
    _num('smoother_speed_scale_sigma', 0.05, "smoother: prior std of the speed source's scale (a wheel radius off by "
                                             'a percent, which its covariance does not show), estimated where vergence '
                                             'measurements give the metric scale too; 0 = the source is exact',
         ge=0.0, le=1.0),
    _bool('constant_speed', True, "every step at one speed (refinement 'local'): the trajectory's shape without "
                                  "the lever arm's unreliable lengths, and a deterministic gauge for the scale the "
                                  'rays leave free; the scale stays unobserved (nominal speed) until a vergence '
                                  'measurement (vergence_topic) or a speed source calibrates it. false = the '
                                  "papers' free two-frame lengths (decided by rounding on straights and arcs)"),
    _num('speed_nominal', 0.5, 'm/s assumed until a vergence measurement or a speed source fixes the scale (the '
                               "smoother's step-length gauge; the constant-speed prior's speed)", gt=0.0),
    _num('scale_min_rotation_deg', 15.0, "refinement 'local' with scale_from_rotation: the scale counts as observed "
                                         'once the rig has turned this much',
         ge=0.0, le=3600.0),
    _bool('scale_from_rotation', False, 'count the metric scale as observed after scale_min_rotation_deg of '
                                        "rotation without a scale aid (the papers' assumption; the lever arm "
                                        'carries no scale on straight and constant-curvature motion: docs/results.md '
                                        '"Scale"). false = only a scale aid makes it observed; until then '
                                        '/fixego/odom carries a large covariance'),
)

# estimator_node: the speed aid (default and text from pipeline.odometry, where SpeedSettings reads them)
SPEED_PARAMS: Table = _table(
    _str('speed_topic', *_SPEED_TEXTS['speed_topic']),
    _num('speed_default_std', *_SPEED_TEXTS['speed_default_std'], gt=0.0, le=1000.0),
    _num('speed_max_age_s', *_SPEED_TEXTS['speed_max_age_s'], gt=0.0, le=3600.0),
)

CAMERA_NODE_PARAMS: Table = _table(
    _str('side', 'right', 'which camera: right | left (topic prefix and joint names)', choices=SIDES),
    _str('port', '', 'VISCA serial device; empty = passive mode (no serial port)'),
    _num('baud', 9600, 'serial baud rate (EVI cameras: 9600)', ge=1200, le=115200),
    _num('address', 1, 'VISCA camera address 1..7', ge=1, le=7),
    _str('profile', 'evi_d30', 'camera profile: evi_d30 | evi_d100 | evi_d70 | evi_g20 | path to calibrate .json'),
    _bool('require_model_match', False, "on connect the camera's model (CAM_VersionInq) is compared with the "
                                        "profile's model ids: true = a mismatch stops the node; false = it is "
                                        'logged and an ERROR on /diagnostics. No answer: a WARN either way'),
    _bool('passive', False, 'follow recorded joint states and only track (replays); also implied by empty port'),
    _str('video_device', '', 'V4L2 device (index or path) read with OpenCV instead of subscribing image_raw'),
    _num('video_fps', 30.0, 'frame rate to poll video_device at', gt=0.0, le=1000.0),
    _str('rig_file', '', RIG_FILE),
    _num('camera_info_wait_s', 30.0, 'when the rig file gives no intrinsics for a camera this node needs: wait at '
                                     'most this long (s) at start for its camera_info', ge=0.0, le=3600.0),
    _num('serial_timeout_s', 0.3, 'bound on every serial reply wait', gt=0.0, le=MAX_TIMEOUT_S),
    _num('servo_gain', 0.9, 'fraction of the angular error corrected per command', gt=0.0, le=2.0, live=True),
    _num('servo_deadband_px', 0.75, 'no command while the fixation is this close to the principal point', ge=0.0,
         live=True),
    _num('servo_move_time_s', 0.08, 'speed codes chosen so a correction takes about this long', gt=0.0, le=60.0,
         live=True),
    _num('servo_max_command_rate_hz', 15.0, 'AbsolutePosition commands per second at most (serial bandwidth)',
         gt=0.0, le=1000.0, live=True),
    _bool('servo_feedforward', True, 'lead a drifting fixation point by its estimated angular rate', live=True),
    FIXATION_PARAMS,
    _num('limit_margin_deg', 5.0, 'when pan/tilt comes this close to a limit, the head swings back and a new '
                                  'fixation point is selected there', ge=0.0, le=90.0, live=True),
    _num('limit_swing_deg', 60.0, 'how far the head swings back from a limit (towards the middle of the range, not '
                                  'past it); no fixation is published while it turns (EVI-D30: ~1 s for 60 deg)',
         gt=0.0, le=360.0, live=True),
    _num('limit_hold_max_s', 1.0, "a swing back from a limit waits while the other camera publishes no fixation (it "
                                  'is swinging too, lost its point, or a vergence step drives it), up to this long, '
                                  'so the two cameras are never both without a fixation; 0 = swing at once',
         ge=0.0, le=10.0, live=True),
    _str('joint_mode', 'predict', 'joint state at each image stamp: predict = at once, interpolated when a '
                                  'PosInq reading after the stamp exists, else predicted from the last reading and '
                                  "the servo's own commands (1-sigma in effort); wait = only once a reading after "
                                  'the stamp exists (interpolated; 25-50 ms at 9600 baud)',
         choices=JOINT_MODES, live=True),
    _num('joint_predict_max_s', 0.1, 'predict mode: no prediction further than this (s) past the last reading; such '
                                     'a stamp waits as in wait mode', gt=0.0, le=1.0, live=True),
    _num('joint_max_wait_s', 0.25, 'how long an image stamp may wait for the PosInq reading after it', ge=0.0,
         le=60.0, live=True),
    _diagnostics_period(),
    _bool('vergence_enabled', True, "left node only, active mode: vergence steps - the left head fixates the right "
                                    "camera's point too and publishes its triangulated distance on /fixego/vergence "
                                    '(scale aid) at start-up, on each new right fixation point, on '
                                    '/fixego/vergence_request and every vergence_period_s; the right node ignores it'),
    _num('vergence_period_s', 0.0, 'also a vergence step this often (s, from the start of the last); 0 = off', ge=0.0,
         le=86400.0, live=True),
    _num('vergence_min_interval_s', 2.0, 'at least this long (s) from the end of a vergence step that left the own '
                                         'fixation to the start of the next, whatever triggers it (bounds how often '
                                         'the own fixation is left)',
         ge=0.0, le=86400.0, live=True),
    _num('vergence_retry_s', 5.0, 'a failed vergence step is retried at the next trigger or after this back-off (s), '
                                  'doubled per failure in a row up to 60 s', gt=0.0, le=3600.0, live=True),
    _num('vergence_frames', 20, 'frames averaged into one vergence measurement once both fixations have settled',
         ge=1, le=300),
    _num('vergence_wait_s', 10.0, 'bound on waiting for both fixations to settle (the left keeps its own point)',
         gt=0.0, le=3600.0),
    _num('vergence_max_interruption_s', 1.8, "bound on a vergence step's head moves, predicted from the profile's "
                                             'top speeds: out to the right fixation point, the image searched there '
                                             'and back (s; the left has no fixation meanwhile). A longer step is '
                                             'refused before the head moves; a further aim or centring move that '
                                             'would exceed it is not made. 1.8 s: a 60 deg trip on an EVI-D30 '
                                             '(80 deg/s)', gt=0.0, le=60.0),
    _num('vergence_timeout_s', 5.0, 'bound from leaving the own fixation to the measurement; then the head returns',
         gt=0.0, le=3600.0),
    _num('vergence_settle_px', 60.0, 'vergence: both fixations this close to their principal points (3 frames in a '
                                     'row, then every averaged frame)', gt=0.0),
    _num('vergence_max_rate_deg_s', 60.0, 'vergence: and both heads turning at most this fast (a moving head\'s '
                                         'reading is quantised and its time uncertain)', gt=0.0, le=1000.0),
    _num('vergence_min_depth_m', 0.8, 'nearest depth searched along the right fixation ray', gt=0.0),
    _num('vergence_max_depth_m', 10.0, 'farthest depth searched along the right fixation ray', gt=0.0),
    _num('vergence_ncc_min', 0.8, 'partner point: best NCC below this is no match', ge=-1.0, le=1.0),
    _num('vergence_match_ncc_min', 0.95, 'partner point: its refined match correlating below this is not measured '
                                         '(such steps were 1-13 % off)', ge=-1.0, le=1.0),
    _num('vergence_margin_min', 0.1, 'partner point: best minus second-best NCC peak below this is ambiguous',
         ge=0.0, le=2.0),
    _num('vergence_max_rel_std', 0.05, 'vergence: a measurement whose std exceeds this share of its distance is not '
                                       'published (the step fails; near the baseline its std understates: 5 demo '
                                       'steps 21-72 % off were all above 5 %, docs/results.md "Stop 85")', gt=0.0,
         le=1.0),
    _num('vergence_pixel_sigma_px', 0.3, 'vergence: pixel noise of the two fixations used for the covariance (one '
                                         'correspondence per step: not reduced by averaging)', gt=0.0),
    _num('vergence_joint_sigma_deg', 0.033, 'vergence: reading noise of a moving head used for the covariance (EVI-D30 '
                                            'unit / sqrt 12; a head at rest reads exactly)', gt=0.0),
    _num('vergence_timing_sigma_ms', 5.0, 'vergence: time uncertainty of a joint reading at an image stamp, times the '
                                         "head's rate for the covariance (the demo's readings: -1.2 to +2.9 ms p10-p90 "
                                         'while turning, docs/results.md "Stop 36")', gt=0.0, le=1000.0),
    _num('vergence_timing_bias_ms', 1.0, 'vergence: a time error of the joint readings common to all frames of a step '
                                        "(it does not average out), times the heads' rates for the covariance (on the "
                                        "demo's arcs the left head's readings lagged 0.2-1.8 ms over a step, "
                                        'docs/results.md "Stop 78")', ge=0.0, le=1000.0),
)

FLOW_NODE_PARAMS: Table = _table(
    _str('rig_file', '', RIG_FILE),
    FLOW_PARAMS,
    _str('observation_topic', 'flow/observation', 'where observations are published (relative: in the node '
                                               'namespace, default /fixego)'),
    _num('max_lag_s', 0.0, 'when the node is behind its input, a ready frame older than this (s after its stamp) '
                           'with a newer one ready is skipped and the newest processed (frames_skipped on '
                           '/diagnostics); 0 = always the newest. Bounds the latency when the front end takes longer '
                           'than a frame period', ge=0.0, le=60.0, live=True),
    _diagnostics_period(),
)

ESTIMATOR_NODE_PARAMS: Table = _table(
    _str('rig_file', '', RIG_FILE),
    _num('camera_info_wait_s', 30.0, 'when the rig file gives no intrinsics for a camera this node needs: wait at '
                                     'most this long (s) at start for its camera_info', ge=0.0, le=3600.0),
    _str('observation_topic', 'flow/observation', 'flow observations (PointCloud2 rows, see README; relative: in '
                                               'the node namespace)'),
    ESTIMATOR_PARAMS,
    SPEED_PARAMS,
    _num('max_lag_s', 0.1, "when a non-keyframe observation has waited this long in this node's queue (the node is "
                           'behind its input), skip it; an observation that came late but finds the node idle is '
                           "posed (where the middleware gives no receive time: its age on the node's clock decides). "
                           'Keyframes are always solved: the trajectory continues through them', ge=0.0, live=True),
    _num('max_keyframe_lag_s', 0.5, 'even keyframes are skipped this far behind (the estimator then bridges the gap '
                                    'at constant velocity): bounds the latency when the machine is overloaded',
         ge=0.0, live=True),
    _num('smoother_warn_behind_s', 1.0, 'warn (logged once, WARN on /diagnostics until it is back under half of '
                                        'this) when the smoother process\'s newest result lags the newest frame by '
                                        'more than this (s): the machine does not keep up, so the path is revised '
                                        'late and from keyframes alone, which lost 2 of 9 test bags (docs/results.md '
                                        '"Stop 66"); 0 = never', ge=0.0, live=True),
    _num('max_future_s', 1.0, 'an observation stamped this far ahead of the node clock is rejected and counted '
                              '(a wrong clock would otherwise make every later observation out of order)', gt=0.0,
         live=True),
    _num('backward_reset_count', 10, 'this many observations in a row older than the last accepted one (the clock '
                                     'jumped back, e.g. a bag restarted) reset the trajectory', ge=1, le=100000,
         live=True),
    _num('backward_reset_s', 2.0, '... as does an unbroken run of such observations lasting this long (s)', gt=0.0,
         le=3600.0, live=True),
    _str('vergence_topic', 'vergence', "vergence measurements (geometry_msgs/PoseWithCovarianceStamped from the left "
                                       "camera_node's repeated vergence step); '' = off"),
    _str('vergence_request_topic', 'vergence_request', 'std_msgs/Empty published when the scale uncertainty has '
                                                       'grown past vergence_request_rel_std (the left camera_node '
                                                       "then verges); '' = never"),
    _num('vergence_request_rel_std', 0.05, 'relative scale std (grown by scale_drift_per_s since the last '
                                           'measurement) above which a vergence step is requested', gt=0.0,
         live=True),
    _num('vergence_request_min_interval_s', 5.0, 'at most one vergence request per this many seconds', gt=0.0,
         live=True),
    _num('scale_drift_per_s', 0.005, 'relative scale std added per second since the last scale measurement (the '
                                     'speed changes; the fixations change)', ge=0.0, live=True),
    _str('odom_frame', 'odom', 'frame of the published trajectory'),
    _str('base_frame', 'base_link', "the robot's base frame (x forward, y left, z up): child of the published "
                                    "odometry, parent of the rig file's rig_in_base_link, frame of speed_topic's "
                                    'twist'),
    _num('path_max_length', 5000, 'poses kept in path and path_raw (oldest dropped; each Path message carries them '
                                  'all, so its cost grows with this)', ge=1, le=10_000_000),
    _num('path_publish_period_s', 1.0, 'path and path_raw are published at most once per this much observation '
                                       'time, and once more when no observation has come for this long of wall time '
                                       '(the end of a run); pose and odom go out every frame. 0 = paths every frame',
         ge=0.0, le=3600.0),
    _str('publish_tf', 'auto', "broadcast odom -> base_frame when tf2_ros is importable: 'true', 'false', or "
                               "'auto' = only when no speed source is configured (speed_topic empty; a robot with "
                               'wheel odometry usually publishes that transform itself)',
         choices=('auto', 'true', 'false')),
    _bool('publish_static_tf', True, "broadcast the static base_frame -> rig (the rig file's rig_in_base_link) and "
                                     'rig -> right_zero / left_zero (left_in_rig) when tf2_ros is importable; '
                                     "false when the robot's URDF already has them"),
    _diagnostics_period(),
)

SIM_RIG_NODE_PARAMS: Table = _table(
    _str('trajectory', 'paper', f'trajectory: {", ".join(TRAJECTORIES)}', choices=TRAJECTORIES),
    _num('speed', 0.0, 'rig speed in m/s (0: the trajectory default)', ge=0.01, le=100.0, also=(0.0,)),
    _num('duration', 0.0, 'truncate the trajectory to this many seconds (0: whole)', ge=0.0, le=3600.0),
    _num('rest_end_s', 0.0, 'the rig stands still this long at its last pose after the trajectory (s)',
         ge=REST_RANGE[0], le=REST_RANGE[1]),
    _num('fps', 30.0, 'frame rate of both cameras', gt=0.0, le=1000.0),
    _num('time_scale', 1.0, 'trajectory seconds per wall-clock second (0 freezes the rig)', ge=0.0, le=1000.0),
    _str('rig_file', '', 'rig calibration file (empty: config/rig.yaml)'),
    _num('width', 0, 'image width (0: the rig file; intrinsics scaled)', ge=0, le=16384),
    _num('height', 0, 'image height (0: the rig file; intrinsics scaled)', ge=0, le=16384),
    _num('hfov_deg', 0.0, 'horizontal angle of view in deg (0: the rig file; papers: 21)', ge=0.0, lt=180.0),
    _num('seed', 0, 'seed of textures, noise and the random trajectory', ge=0, le=2**32 - 1),
    _str('encoding', 'mono8', 'mono8 or rgb8', choices=('mono8', 'rgb8')),
    _num('noise_sigma', 2.0, 'sensor noise sigma in grey levels', ge=0.0, le=255.0),
    _num('texel', 0.002, 'texture resolution in m', ge=0.001, le=1.0),
    _bool('loop', False, 'restart the trajectory at its end'),
    _bool('exit_at_end', True, 'shut the node down when the trajectory ends (not looping)'),
    _bool('wait_for_start', False, 'hold the rig at the start pose (still rendering) until ~/start is called, so '
                                   'the other nodes can come up and fixate first'),
    _str('pty_file', '/tmp/fixego_sim_ptys.json', 'JSON file receiving the two pty paths'),
    _str('pty_link_dir', '', "also make symlinks <dir>/right and <dir>/left to the ptys (camera_node ports known "
                             "before the node starts; sim.launch.py); '' = none"),
    _str('profile', 'evi_d30', 'VISCA camera profile of the emulators'),
    _num('baud', 9600, 'emulated serial baud rate', ge=1200, le=115200),
    _num('start_pan_deg_right', 22.5, 'initial pan of the right head (deg)', ge=-180.0, le=180.0),
    _num('start_pan_deg_left', -22.5, 'initial pan of the left head (deg)', ge=-180.0, le=180.0),
    _num('start_tilt_deg', 0.0, 'initial tilt of both heads (deg)', ge=-90.0, le=90.0),
)

BAG_PLAYER_PARAMS: Table = _table(
    _str('bag', '', 'rosbag2 directory or .mcap file to play'),
    _num('rate', 1.0, 'playback speed factor (2 = twice as fast); 0 = as fast as possible', ge=0.0),
    _bool('loop', False, 'replay the bag from its start when it ends (the /clock time keeps increasing)'),
    _strings('topics', 'topics to play; unset or empty = all'),
    _strings('remap', "topic renames 'FROM:=TO' applied when publishing"),
    _bool('publish_clock', False, "publish rosgraph_msgs/Clock on /clock at each message's bag time"),
    _num('start_delay_s', 0.5, 'wait this long after creating the publishers, for discovery, before the first '
                               'message (s)', ge=0.0, le=3600.0),
    _num('start_offset_s', 0.0, 'skip the first seconds of the bag', ge=0.0),
    _num('ack_timeout_s', 2.0, 'at the end, wait at most this long for reliable subscribers to acknowledge', ge=0.0,
         le=3600.0),
    _diagnostics_period(live=False),
)

BAG_RECORDER_PARAMS: Table = _table(
    _str('bag', '', 'bag directory to create (must not exist); empty = rosbag2_YYYY_MM_DD-HH_MM_SS here'),
    _strings('topics', 'topics to record; unset or empty = every topic discovered'),
    _num('discovery_period_s', 1.0, 'how often the graph is scanned for new topics and publishers (s)', ge=0.05,
         le=3600.0),
    _bool('include_hidden', False, 'with an empty topic list, also record hidden topics (a name part starting '
                                   'with _)'),
    _num('depth', 100, 'subscription queue depth (keep-last)', ge=1, le=100000),
    _bool('compression', True, 'zstd-compress the MCAP chunks'),
    _num('flush_period_s', 1.0, 'close the MCAP chunk and flush the file this often, so a killed recorder leaves '
                                'a readable bag up to then (0 = only at 1 MiB chunks)', ge=0.01, le=3600.0,
         also=(0.0,)),
    _num('diagnostics_period_s', 1.0, 'diagnostics publishing period (s; 0 = none)', also=(0.0,),
         **DIAGNOSTICS_PERIOD[1]),
)

# node name -> its parameters, in the order config/<node>.yaml lists them
NODE_PARAMS: dict[str, Table] = {
    'camera_node': CAMERA_NODE_PARAMS, 'flow_node': FLOW_NODE_PARAMS, 'estimator_node': ESTIMATOR_NODE_PARAMS,
    'sim_rig_node': SIM_RIG_NODE_PARAMS, 'bag_player': BAG_PLAYER_PARAMS, 'bag_recorder': BAG_RECORDER_PARAMS,
}


# ---------------------------------------------------------------------------------------------- builders
def _config_error(what: str, e: ValueError) -> ParamsError:
    """A combination of valid values the core refuses (e.g. paper_region_px > window_px), as one line."""
    return e if isinstance(e, ParamsError) else ParamsError(f'{what} parameters do not fit together: {e}')


def fixation_params(g: Getter) -> FixationParams:
    return FixationParams(search_radius_px=float(g('search_radius_px')), min_corner_score=float(g('min_corner_score')),
                          template_half=int(g('template_half_px')), ncc_min=float(g('ncc_min')),
                          fb_max_px=float(g('fb_max_px')), border_margin_px=float(g('border_margin_px')),
                          relocate_radius_px=float(g('relocate_radius_px')))


def flow_params(g: Getter) -> FlowParams:
    try:
        return FlowParams(preset=str(g('preset')), window_px=int(g('window_px')),
                          paper_region_px=int(g('paper_region_px')), paper_points=int(g('paper_points')),
                          max_corners=int(g('max_corners')), min_eig=float(g('min_eig')),
                          fb_max_px=float(g('fb_max_px')), lk_win=int(g('lk_win')), lk_levels=int(g('lk_levels')),
                          ransac_px=float(g('ransac_px')), register_period_s=float(g('register_period_s')))
    except ValueError as e:
        raise _config_error('flow', e) from None


def keyframe_policy(g: Getter) -> KeyframePolicy:
    try:
        return KeyframePolicy(max_frames=int(g('keyframe_max_frames')),
                              min_parallax_px=float(g('keyframe_min_parallax_px')),
                              min_tracked_fraction=float(g('keyframe_min_tracked_fraction')),
                              max_rotation_deg=float(g('keyframe_max_rotation_deg')))
    except ValueError as e:
        raise _config_error('keyframe', e) from None


def sync_params(g: Getter) -> SyncParams:
    try:
        return SyncParams(slop_s=float(g('slop_s')), max_wait_s=float(g('max_wait_s')),
                          joint_extrapolation_s=float(g('joint_extrapolation_s')))
    except ValueError as e:
        raise _config_error('synchronisation', e) from None


def estimator_config(g: Getter, rig: Rig) -> EstimatorConfig:
    """Pixel-valued parameters are converted with the right camera's focal length."""
    f = rig.camera('right').fx
    try:
        return EstimatorConfig(
            window=int(g('window')), mode=str(g('mode')), fixation_weight=float(g('fixation_weight')),
            joint_sigma_nominal=math.radians(float(g('joint_sigma_nominal_deg'))),
            max_step_translation=float(g('max_step_translation')), max_speed=float(g('max_speed')),
            max_step_rotation=math.radians(float(g('max_step_rotation_deg'))),
            reject_translation_std=float(g('reject_translation_std')), velocity_prior=bool(g('velocity_prior')),
            prior_sigma_rel=float(g('prior_sigma_rel')), prior_sigma_min=float(g('prior_sigma_min')),
            solver=SolverConfig(sigma=float(g('pixel_sigma')) / f, loss=str(g('loss')), max_nfev=int(g('max_nfev')),
                                min_parallax=float(g('stationary_parallax_px')) / f,
                                camera_parallax=float(g('stationary_camera_parallax_px')) / f,
                                head_sigma=math.radians(float(g('stationary_head_sigma_deg'))),
                                backend=str(g('solver_backend'))),
            refinement=str(g('refinement')), scale_min_rotation_deg=float(g('scale_min_rotation_deg')),
            scale_from_rotation=bool(g('scale_from_rotation')),
            constant_speed=bool(g('constant_speed')), speed_nominal=float(g('speed_nominal')),
            smoother=SmootherConfig(lag_s=float(g('smoother_lag_s')), pixel_sigma_px=float(g('pixel_sigma')),
                                    iterations=int(g('smoother_iterations')), gate_px=float(g('smoother_gate_px')),
                                    min_parallax_deg=float(g('smoother_min_parallax_deg')),
                                    twist_rotation_sigma=float(g('smoother_twist_rotation_sigma')),
                                    twist_translation_sigma=float(g('smoother_twist_translation_sigma')),
                                    twist_speed_sigma=float(g('smoother_twist_speed_sigma')),
                                    step_floor_px=float(g('smoother_step_floor_px')),
                                    step_cauchy_k=float(g('smoother_step_cauchy')),
                                    mount_rotation_sigma=float(g('smoother_mount_rotation_sigma')),
                                    forward_sigma_deg=float(g('smoother_forward_sigma_deg')),
                                    speed_scale_sigma=float(g('smoother_speed_scale_sigma')),
                                    nominal_speed=float(g('speed_nominal'))))
    except ValueError as e:
        raise _config_error('estimator', e) from None


# ---------------------------------------------------------------------------------------------- files, getters
_ALL_SPECS: dict[str, list[ParamSpec]] = {}
for _table_ in NODE_PARAMS.values():
    for _spec in _table_.values():
        if _spec not in _ALL_SPECS.setdefault(_spec.name, []):
            _ALL_SPECS[_spec.name].append(_spec)


def spec_of(name: str, entry: ParamSpec | tuple[object, str]) -> ParamSpec:
    """The spec of a table entry. A legacy ``(default, description)`` pair (e.g.
    ``pipeline.odometry.SPEED_PARAMS``) resolves to the node spec of that name and default, so its range
    still applies; one without a spec gets its type from the default and no range."""
    if isinstance(entry, ParamSpec):
        return entry
    default, text = entry
    for spec in _ALL_SPECS.get(name, []):
        if spec.default == default and type(spec.default) is type(default):
            return spec
    t = type(default) if isinstance(default, (bool, int, float, str)) else list
    return ParamSpec(name, default, str(text), t)


def check_values(table: Mapping[str, ParamSpec | tuple[object, str]], values: Mapping[str, object]) -> dict:
    """``values`` with each known name checked against ``table`` (ints for float parameters become floats);
    unknown names are kept as they are (a file may carry other nodes' or newer parameters)."""
    return {k: spec_of(k, table[k]).check(v) if k in table else v for k, v in values.items()}


WILDCARDS = ('/**', '**')


def _node_of(key: object) -> str | None:
    """The node a parameter-file block is for: ``node``, ``/ns/node``, a renamed ``right_camera_node`` (its
    last path segment names or ends with ``_<node>``), the wildcards (``'**'``), or None (unknown)."""
    text = str(key)
    if text in WILDCARDS:
        return '**'
    seg = text.rstrip('/').split('/')[-1]
    for node in NODE_PARAMS:
        if seg == node or seg.endswith('_' + node):
            return node
    return None


def parse_value(name: str, text: str) -> object:
    """A ``-p NAME:=VALUE`` value as ROS reads it (YAML), or :class:`ParamsError` naming the parameter."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        where = f' (line {e.problem_mark.line + 1})' if getattr(e, 'problem_mark', None) else ''
        raise ParamsError(f'parameter {name}: {text!r} is not a YAML value{where}') from None


def read_params_file(path: str | Path) -> dict[str, dict[str, object]]:
    """Every block of a ROS 2 parameter file (``{node: {ros__parameters: {name: value}}}``), checked: the
    structure, the node names, and each parameter against the spec of its node, so a misspelt name or node
    is an error (one line naming the file, the block and the closest known name), not silently ignored."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ParamsError(f'{path}: cannot read parameters ({type(e).__name__}: {reason})') from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ParamsError(f'{path}: not a ROS 2 parameter file (the top level must map node names to '
                          '{ros__parameters: {name: value}})')
    out: dict[str, dict[str, object]] = {}
    for key, block in data.items():
        node = _node_of(key)
        if node is None:
            close = difflib.get_close_matches(str(key), list(NODE_PARAMS), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else f" (known: {', '.join(NODE_PARAMS)}, /**)"
            raise ParamsError(f'{path}: unknown node {key!r}{hint}')
        if not (isinstance(block, dict) and list(block) == ['ros__parameters']
                and isinstance(block['ros__parameters'], dict)):
            raise ParamsError(f'{path}: {key}: expected only ros__parameters: {{name: value, ...}}')
        params = block['ros__parameters']
        tables = list(NODE_PARAMS.values()) if node == '**' else [NODE_PARAMS[node]]
        for name, value in params.items():
            owners = [t[name] for t in tables if name in t]
            if not owners:
                known = sorted({n for t in tables for n in t})
                close = difflib.get_close_matches(str(name), known, n=1)
                hint = f" (did you mean '{close[0]}'?)" if close else ''
                raise ParamsError(f'{path}: {key}: unknown parameter {name!r}{hint}')
            try:
                for spec in owners:
                    spec.check(value)
            except ParamsError as e:
                raise ParamsError(f'{path}: {key}: {e}') from None
        out[str(key)] = dict(params)
    return out


# the line of a generated config/<node>.yaml naming its node: the file's block is keyed /** (so it applies under
# any node name and namespace), and this line tells ``fixego replay``, which reads several nodes' files at once,
# which node the block is for
FILE_NODE = re.compile(r'^# fixego_ros node: (\w+)', re.MULTILINE)


def file_node(path: str | Path) -> str | None:
    """The node a parameter file says it is for (:data:`FILE_NODE`), or None (a wildcard block then applies to
    every node, as in ROS)."""
    try:
        m = FILE_NODE.search(Path(path).read_text())
    except (OSError, UnicodeDecodeError):
        return None
    return m.group(1) if m and m.group(1) in NODE_PARAMS else None


def load_params_file(path: str | Path, node: str) -> dict[str, object]:
    """The values a node named ``node`` takes from a ROS 2 parameter file: the wildcard blocks, then the
    blocks keyed ``node`` or ``/ns/node`` (later wins), each checked against its spec ({} when none applies).
    The wildcard blocks of a file that names another node (:func:`file_node`, e.g. the generated
    ``config/camera_node.yaml`` read for flow_node) do not apply: ``fb_max_px`` means different things to them.
    The whole file is checked (:func:`read_params_file`), so an error elsewhere in it is reported too."""
    table = NODE_PARAMS.get(node, {})
    values: dict[str, object] = {}
    blocks = read_params_file(path)
    owner = file_node(path)
    for key, params in sorted(blocks.items(), key=lambda kv: kv[0] not in WILDCARDS):
        if (key in WILDCARDS and owner in (None, node)) or key.rstrip('/').split('/')[-1] == node:
            values.update({k: v for k, v in params.items() if k in table or key not in WILDCARDS})
    try:
        return check_values(table, values)
    except ParamsError as e:
        raise ParamsError(f'{path}: {node}: {e}') from None


def params_getter(table: Mapping[str, ParamSpec | tuple[object, str]],
                  values: Mapping[str, object] | None = None) -> Getter:
    """Getter over ``table``'s defaults overlaid with ``values``. Unknown names are ignored; every known
    one is checked against its spec (type, range, finite), so ``fixego replay -p``/``--params-file`` refuse
    what the nodes refuse, with the same one-line :class:`ParamsError`."""
    specs = {k: spec_of(k, e) for k, e in table.items()}
    merged: dict[str, object] = {k: s.default for k, s in specs.items()}
    merged.update({k: specs[k].check(v) for k, v in (values or {}).items() if k in specs})
    return merged.__getitem__


# ---------------------------------------------------------------------------------------------- config files
CONFIG_HEADERS: dict[str, str] = {
    'camera_node': 'camera_node parameters (one node per camera: ros2 run fixego_ros camera_node --ros-args '
                   '-p side:=left ...)',
    'flow_node': 'flow_node parameters: ros2 run fixego_ros flow_node --ros-args --params-file config/flow_node.yaml',
    'estimator_node': 'estimator_node parameters: ros2 run fixego_ros estimator_node --ros-args --params-file '
                      'config/estimator_node.yaml',
    'sim_rig_node': 'sim_rig_node parameters (the simulated rig, live): ros2 run fixego_ros sim_rig_node '
                    '--ros-args --params-file config/sim_rig_node.yaml',
    'bag_player': 'bag_player parameters (fixego play runs it): ros2 run fixego_ros bag_player --ros-args '
                  '-p bag:=BAG_DIR',
    'bag_recorder': 'bag_recorder parameters (fixego record runs it): ros2 run fixego_ros bag_recorder '
                    '--ros-args -p bag:=BAG_DIR',
}


def _yaml_scalar(value: Value) -> str:
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return json.dumps(value)
    return yaml.safe_dump(value, default_flow_style=True).removesuffix('\n...\n').strip()


def render_config(node: str) -> str:
    """``config/<node>.yaml``: every parameter with its default, description, range and whether it can
    change at run time (unset string arrays appear commented out)."""
    lines = [f'# {CONFIG_HEADERS[node]}',
             '# Generated from fixego_ros/pipeline/params.py (python -m fixego_ros.pipeline.params --write-config '
             'config/);',
             '# edit the spec there, not this file. [...] gives the allowed values; read-only parameters are taken '
             'at start only.',
             '# Keyed /** so the values apply whatever the node is named (-r __node:=right_camera_node) and in any '
             'namespace.',
             f'# fixego_ros node: {node} (fixego replay --params-file gives this block to {node} only)',
             '/**:', '  ros__parameters:']
    for spec in NODE_PARAMS[node].values():
        note = f'{spec.description} [{spec.allowed()}{"; read-only" if spec.read_only else ""}]'
        if spec.default is None:
            lines.append(f'    # {spec.name}: []  # {note}')
        else:
            lines.append(f'    {spec.name}: {_yaml_scalar(spec.default)}  # {note}')
    return '\n'.join(lines) + '\n'


def write_config(directory: str | Path) -> list[Path]:
    """Write ``<node>.yaml`` of every node into ``directory``; the paths written."""
    out = []
    for node in NODE_PARAMS:
        path = Path(directory) / f'{node}.yaml'
        path.write_text(render_config(node))
        out.append(path)
    return out


# ---------------------------------------------------------------------------------------------- reference
def _cell(text: str) -> str:
    return text.replace('|', '\\|').replace('\n', ' ')


def _type_name(spec: ParamSpec) -> str:
    return {bool: 'bool', int: 'int', float: 'float', str: 'string', list: 'string[]'}[spec.type]


def _default_text(spec: ParamSpec) -> str:
    if spec.default is None:
        return '(unset)'
    if isinstance(spec.default, str):
        return f'`{json.dumps(spec.default)}`'
    return f'`{_yaml_scalar(spec.default)}`'


def render_docs() -> str:
    """``docs/parameters.md``: one table per node (name, type, default, allowed, when it applies, description)."""
    lines = ['# Parameter reference', '',
             'Generated from the specs in `fixego_ros/pipeline/params.py` '
             '(`python -m fixego_ros.pipeline.params --write-docs docs/parameters.md`); edit the specs, not this file. '
             '*read-only*: taken at start only; *run-time*: `ros2 param set` applies it to the running node. '
             'Every value is checked (type, range, finite) at start and on every change; a refused value is one '
             'line naming the parameter and what is allowed.', '']
    for node, table in NODE_PARAMS.items():
        lines += [f'## {node}', '', '| name | type | default | allowed | changes | description |',
                  '|---|---|---|---|---|---|']
        for spec in table.values():
            when = 'read-only' if spec.read_only else 'run-time'
            lines.append(f'| `{spec.name}` | {_type_name(spec)} | {_cell(_default_text(spec))} | '
                         f'{_cell(spec.allowed())} | {when} | {_cell(spec.description)} |')
        lines.append('')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='python -m fixego_ros.pipeline.params',
                                description='Generate (or check) config/<node>.yaml and the parameter reference '
                                            'from the parameter specs.')
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument('--write-config', type=Path, metavar='DIR', help='write DIR/<node>.yaml for every node')
    g.add_argument('--check-config', type=Path, metavar='DIR', help='exit 1 if DIR/<node>.yaml differ from the specs')
    g.add_argument('--write-docs', type=Path, metavar='FILE', help='write the parameter reference (markdown) to FILE')
    g.add_argument('--check-docs', type=Path, metavar='FILE', help='exit 1 if FILE differs from the specs')
    args = p.parse_args(argv)
    if args.write_config is not None:
        for path in write_config(args.write_config):
            print(f'wrote {path}')
        return 0
    if args.write_docs is not None:
        args.write_docs.write_text(render_docs())
        print(f'wrote {args.write_docs}')
        return 0
    if args.check_docs is not None:
        if args.check_docs.is_file() and args.check_docs.read_text() == render_docs():
            return 0
        print(f'{args.check_docs} differs from the specs (regenerate with --write-docs)', file=sys.stderr)
        return 1
    stale = [node for node in NODE_PARAMS if not (args.check_config / f'{node}.yaml').exists()
             or (args.check_config / f'{node}.yaml').read_text() != render_config(node)]
    for node in stale:
        print(f'{args.check_config / node}.yaml differs from the specs (regenerate with --write-config)',
              file=sys.stderr)
    return 1 if stale else 0


if __name__ == '__main__':
    sys.exit(main())
