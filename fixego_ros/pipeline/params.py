"""The tunable parameters of tracking, flow and estimation, shared by the nodes and ``fixego replay``.

Each table maps ``name -> (default, description)``; the nodes declare them as ROS parameters (with the
description as descriptor) and ``config/<node>.yaml`` repeats the defaults. The builders turn any
``get(name)`` callable (a node's parameter getter, or :func:`params_getter` over a YAML file) into the
core's config objects, so a replay runs with exactly what the live nodes would use.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import yaml

from fixego_ros.estimation.estimator import EstimatorConfig
from fixego_ros.estimation.sliding_window import WindowConfig
from fixego_ros.estimation.twoframe import SolverConfig
from fixego_ros.geometry.rig import Rig
from fixego_ros.pipeline.frontend import KeyframePolicy
from fixego_ros.pipeline.sync import SyncParams
from fixego_ros.tracking.fixation import FixationParams
from fixego_ros.tracking.flow import FlowParams

Getter = Callable[[str], object]
Table = dict[str, tuple[object, str]]

# camera_node: the fixation point tracker
FIXATION_PARAMS: Table = {
    'search_radius_px': (60.0, 'fixation selection window radius around the centre'),
    'min_corner_score': (2e-4, 'minimum corner (min-eigenvalue) score of a fixation point'),
    'template_half_px': (10, 'half size of the NCC validity template'),
    'ncc_min': (0.7, 'template correlation below which the track counts as lost'),
    'fb_max_px': (1.0, 'forward-backward LK error above which the track counts as lost'),
    'border_margin_px': (40.0, 're-select when the fixation comes this close to the image border'),
}

# flow_node: synchronisation, flow tracking and keyframes
FLOW_PARAMS: Table = {
    'preset': ('window', "flow points: 'paper' (3 in the central 30x30 px), 'window' (all good corners in "
                         "the window), 'full' (whole image)"),
    'window_px': (100, 'side of the flow window centred on the fixation point (px)'),
    'paper_region_px': (30, "paper preset: side of the central region the points are drawn from (px)"),
    'paper_points': (3, 'paper preset: points per camera'),
    'max_corners': (80, 'window/full presets: most corners tracked per camera (the solve time grows with it)'),
    'min_eig': (1e-3, 'Lucas-Kanade minimum-eigenvalue threshold (rejects untextured points)'),
    'fb_max_px': (0.5, 'forward-backward consistency bound (px)'),
    'lk_win': (21, 'Lucas-Kanade window (px)'),
    'lk_levels': (3, 'pyramid levels'),
    'ransac_px': (1.0, "epipolar RANSAC inlier bound per camera, keyframe -> now (px; 0 = off)"),
    'keyframe_max_frames': (10, 'frames tracked from one keyframe at most (1 = consecutive frames, the papers)'),
    'keyframe_min_parallax_px': (0.0, 'new keyframe once the rotation-compensated parallax reaches this (0 = off)'),
    'keyframe_min_tracked_fraction': (0.5, "new keyframe when fewer of the keyframe's points still track"),
    'keyframe_max_rotation_deg': (8.0, 'new keyframe once the rig rotation since the keyframe exceeds this '
                                       '(deg; 0 = off)'),
    'slop_s': (0.01, 'images of the two cameras closer than this form one frame (s)'),
    'max_wait_s': (0.25, 'bound on waiting for a partner image, joint state or fixation (s)'),
    'joint_extrapolation_s': (0.0, 'how far past the newest joint state an image may be (s); 0 = wait for one'),
}

# estimator_node: two-frame solve and local bundle adjustment
ESTIMATOR_PARAMS: Table = {
    'refinement': ('local', "'local': the papers' local BA of the latest step over `window` frames; 'sliding': "
                            "the last `sliding_frames` keyframe poses refined with persistent landmarks"),
    'window': (3, 'n: frames in the local bundle adjustment (3..10; 0 disables it)'),
    'mode': ('paper', "local BA: 'paper' (BA cost alone, Powell, as in the papers) or 'joint' (+ two-frame terms)"),
    'fixation_weight': (1.0, 'weight of the fixation constraints relative to one flow point'),
    'stationary_parallax_px': (0.3, 'median rotation-compensated parallax (px) below which the rig is taken as '
                                     'standing still (T = 0): with no parallax the scale is pure noise'),
    'pixel_sigma': (1.0, 'expected flow/fixation noise in pixels (sets the covariance scale)'),
    'loss': ('huber', 'robust loss of the two-frame solve: linear | huber | soft_l1 | cauchy | arctan'),
    'velocity_prior': (False, 'weak constant-velocity prior on each step (keeps unobserved scale from wandering; '
                             'the covariance stays the rays\' own). false = the papers\' method'),
    'prior_sigma_rel': (0.5, 'prior std as a fraction of the predicted step length'),
    'prior_sigma_min': (0.01, 'prior std at least this (m)'),
    'max_nfev': (30, 'bound on function evaluations of one two-frame solve'),
    'solver_backend': ('lm', "least squares of the two-frame solve and the least-squares BA modes: 'lm' (our "
                             "compact Levenberg-Marquardt, ~3x faster) or 'scipy' (scipy.optimize.least_squares trf)"),
    'max_step_translation': (0.5, 'm; a larger step is rejected as a jump and predicted instead'),
    'max_speed': (1.5, 'm/s; a step implying a faster rig is rejected as a jump and predicted instead'),
    'max_step_rotation_deg': (20.0, 'deg; a larger step rotation is rejected as a jump'),
    'reject_translation_std': (1e6, 'm; a step whose translation std exceeds this is rejected (1e6: never)'),
    'sliding_frames': (4, 'sliding refinement: keyframe poses refined together (older ones stay fixed)'),
    'sliding_max_unobserved_frames': (40, 'sliding refinement: while the scale is unobserved the window grows up '
                                          'to this, so the first turn can fix the scale of the start'),
    'sliding_iterations': (4, 'sliding refinement: Levenberg-Marquardt iterations per keyframe'),
    'sliding_step_weight': (0.5, 'sliding refinement: weight of the two-frame step factors (0 = landmarks only)'),
    'sliding_min_parallax_deg': (1.0, 'sliding refinement: a landmark is placed once its rays span this angle'),
    'constant_speed': (False, "every step at one speed (refinement 'local'): the trajectory's shape without the "
                              "lever arm's unreliable lengths; the scale stays unobserved (nominal speed) until a "
                              'vergence measurement (vergence_topic) calibrates it. false = the papers\' method'),
    'speed_nominal': (0.5, 'constant-speed prior: m/s assumed until the vergence step measures the speed'),
    'scale_min_rotation_deg': (15.0, 'sliding refinement: the window grows until the rig has turned this much (with '
                                     'scale_from_rotation the scale then also counts as observed)'),
    'scale_from_rotation': (False, 'count the metric scale as observed after scale_min_rotation_deg of rotation '
                                   'without a scale aid (the papers\' assumption; the lever arm carries no scale on '
                                   'straight and constant-curvature motion: README "Scale"). false = only a scale aid '
                                   'makes it observed; until then /fixego/odom carries a large covariance'),
}


def fixation_params(g: Getter) -> FixationParams:
    return FixationParams(search_radius_px=float(g('search_radius_px')), min_corner_score=float(g('min_corner_score')),
                          template_half=int(g('template_half_px')), ncc_min=float(g('ncc_min')),
                          fb_max_px=float(g('fb_max_px')), border_margin_px=float(g('border_margin_px')))


def flow_params(g: Getter) -> FlowParams:
    return FlowParams(preset=str(g('preset')), window_px=int(g('window_px')),
                      paper_region_px=int(g('paper_region_px')), paper_points=int(g('paper_points')),
                      max_corners=int(g('max_corners')), min_eig=float(g('min_eig')), fb_max_px=float(g('fb_max_px')),
                      lk_win=int(g('lk_win')), lk_levels=int(g('lk_levels')), ransac_px=float(g('ransac_px')))


def keyframe_policy(g: Getter) -> KeyframePolicy:
    return KeyframePolicy(max_frames=int(g('keyframe_max_frames')),
                          min_parallax_px=float(g('keyframe_min_parallax_px')),
                          min_tracked_fraction=float(g('keyframe_min_tracked_fraction')),
                          max_rotation_deg=float(g('keyframe_max_rotation_deg')))


def sync_params(g: Getter) -> SyncParams:
    return SyncParams(slop_s=float(g('slop_s')), max_wait_s=float(g('max_wait_s')),
                      joint_extrapolation_s=float(g('joint_extrapolation_s')))


def estimator_config(g: Getter, rig: Rig) -> EstimatorConfig:
    """Pixel-valued parameters are converted with the right camera's focal length."""
    f = rig.camera('right').fx
    return EstimatorConfig(
        window=int(g('window')), mode=str(g('mode')), fixation_weight=float(g('fixation_weight')),
        max_step_translation=float(g('max_step_translation')), max_speed=float(g('max_speed')),
        max_step_rotation=math.radians(float(g('max_step_rotation_deg'))),
        reject_translation_std=float(g('reject_translation_std')), velocity_prior=bool(g('velocity_prior')),
        prior_sigma_rel=float(g('prior_sigma_rel')), prior_sigma_min=float(g('prior_sigma_min')),
        solver=SolverConfig(sigma=float(g('pixel_sigma')) / f, loss=str(g('loss')), max_nfev=int(g('max_nfev')),
                            min_parallax=float(g('stationary_parallax_px')) / f, backend=str(g('solver_backend'))),
        refinement=str(g('refinement')), scale_min_rotation_deg=float(g('scale_min_rotation_deg')),
        scale_from_rotation=bool(g('scale_from_rotation')),
        constant_speed=bool(g('constant_speed')), speed_nominal=float(g('speed_nominal')),
        sliding=WindowConfig(frames=int(g('sliding_frames')),
                             max_unobserved_frames=int(g('sliding_max_unobserved_frames')),
                             iterations=int(g('sliding_iterations')), sigma=float(g('pixel_sigma')) / f,
                             step_weight=float(g('sliding_step_weight')),
                             min_parallax_deg=float(g('sliding_min_parallax_deg'))))


class ParamsError(ValueError):
    """A parameter file or override that does not fit the tables."""


def load_params_file(path: str | Path, node: str) -> dict[str, object]:
    """``ros__parameters`` of ``node`` in a ROS 2 parameter YAML file ({} when the file has no such node)."""
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ParamsError(f'{path}: cannot read parameters ({type(e).__name__}: {e})') from None
    for key in (node, f'/{node}', '/**', '**'):
        block = data.get(key) if isinstance(data, dict) else None
        if isinstance(block, dict) and isinstance(block.get('ros__parameters'), dict):
            return dict(block['ros__parameters'])
    return {}


def params_getter(table: Table, values: dict[str, object] | None = None) -> Getter:
    """Getter over ``table``'s defaults overlaid with ``values`` (unknown names are ignored, with the
    types of the defaults enforced so a YAML typo fails here with its name rather than deep inside)."""
    merged = {k: v for k, (v, _) in table.items()}
    for k, v in (values or {}).items():
        if k not in table:
            continue
        default = table[k][0]
        ok = isinstance(v, type(default)) or (isinstance(default, float) and isinstance(v, int)
                                               and not isinstance(v, bool))
        if not ok:
            raise ParamsError(f'parameter {k}: expected {type(default).__name__}, got {v!r}')
        merged[k] = v
    return merged.__getitem__
