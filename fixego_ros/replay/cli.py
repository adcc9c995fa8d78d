"""``fixego replay BAG_DIR --out EST.tum``: offline tracking + flow + estimation over an image-level bag.

Writes ``EST.tum`` (refined) and ``EST.raw.tum`` (two-frame only): TUM lines ``stamp tx ty tz qx qy qz
qw``, the pose of ``base_link`` in ``odom`` (DESIGN.md §6). Prints what was skipped and why, the speed
against real time, and the ATE when the bag holds ``ground_truth/pose``. ``--speed-topic`` (off by
default) feeds a nav_msgs/Odometry speed source recorded in the bag (e.g. ``fixego sim --wheel-odom-std``)
to the estimator as a scale aid; the vergence measurements (``<namespace>/vergence``, any number, written by
the rig's repeated vergence step and by ``fixego sim``) are used when the bag has them (``--vergence-topic``
names another topic, ``''`` turns them off). The fixations are the bag's ``<side>/fixation`` messages when it has
both (a bag recorded on the rig: the points the heads fixated), else a passive tracker finds them in the images
(``--fixations tracked`` forces that). A bag of the estimator's own inputs (``<namespace>/flow/observation``,
no images: what ``fixego demo`` writes as ``estimator_inputs/``, or ``fixego record`` of that topic on a rig)
replays the estimator alone on the live flow node's observations (``--inputs``).

Exit codes: 0 done (possibly with documented degradations, printed); 2 the bag or the options cannot be
used, or the bag is corrupt: then what precedes the first damaged record has been replayed and written
like a cut recording's, and the last line on stderr says ``BAG: corrupt: where: what``; 128 + the signal
number (130 Ctrl-C, 143 SIGTERM) when interrupted: the estimator process is ended, one line is printed, and
no output file is left half written (TUM files are replaced atomically). Errors are one line, never a
traceback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import sys
from pathlib import Path

from fixego_ros.cli_options import OptionError, check_out_file
from fixego_ros.interrupt import signals_interrupt

PROG = 'fixego replay'
FIXATION_CHOICES = ('recorded', 'tracked')    # replay.run.FixationSource's values (not imported: quick --help)
INPUT_CHOICES = ('images', 'observations')     # replay.run.ReplayInput's values
# node parameters that replay takes as options instead
REPLAY_OPTION = {'vergence_topic': 'use --vergence-topic', 'rig_file': 'use --rig',
                 'observation_topic': 'replay reads <namespace>/flow/observation with --inputs observations; see '
                                      '--remap and --namespace'}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'replay', help='estimate the trajectory of an image-level bag offline (no DDS), write TUM files',
        description='Run passive fixation tracking, flow and estimation over a rosbag2/MCAP bag with the '
                    'topics of DESIGN.md §3 (remappable) and write EST.tum and EST.raw.tum. Deterministic: the '
                    'same bag and options give the same bytes.')
    p.add_argument('bag', type=Path, metavar='BAG_DIR', help='rosbag2 directory (or a single .mcap file)')
    p.add_argument('--out', required=True, type=Path, metavar='EST.tum', help='refined trajectory to write; the '
                   'two-frame one goes next to it as EST.raw.tum')
    p.add_argument('--rig', type=Path, metavar='RIG.yaml', help='rig calibration (default: BAG_DIR/rig.yaml)')
    p.add_argument('--params-file', type=Path, action='append', default=[], metavar='YAML',
                   help='ROS 2 parameter file(s) with camera_node/flow_node/estimator_node blocks (e.g. '
                        'config/*.yaml); later files and the options below override')
    p.add_argument('--preset', choices=('paper', 'window', 'full'), help='flow points (flow_node preset)')
    p.add_argument('--window', type=int, help='local BA window n (3..10; 0 = two-frame only), with '
                                              '-p refinement:=local only')
    p.add_argument('--mode', choices=('paper', 'joint'), help='local BA mode, with -p refinement:=local only')
    p.add_argument('--keyframe-max-frames', type=int, metavar='K', help='frames tracked from one keyframe at most')
    p.add_argument('-p', '--param', action='append', default=[], metavar='NAME:=VALUE',
                   help='any camera_node/flow_node/estimator_node parameter, YAML value (repeatable)')
    p.add_argument('--namespace', default='/fixego', help='topic namespace of the inputs (default /fixego)')
    p.add_argument('--remap', action='append', default=[], metavar='FROM:=TO',
                   help='read contract topic FROM (e.g. /fixego/right/image_raw) from bag topic TO (repeatable)')
    p.add_argument('--speed-topic', metavar='TOPIC',
                   help='scale aid: feed this nav_msgs/Odometry topic of the bag (twist in base_link, e.g. '
                        '/fixego/wheel/odom) to the estimator (estimator_node speed_topic; default: off)')
    p.add_argument('--speed-default-std', type=float, metavar='M_S',
                   help='std (m/s) of a speed sample whose covariance is all zeros (estimator_node '
                        'speed_default_std)')
    p.add_argument('--vergence-topic', metavar='TOPIC',
                   help='scale aid: feed the vergence measurements on this geometry_msgs/PoseWithCovarianceStamped '
                        'topic of the bag (the right fixation point in the rig frame at each stamp) to the '
                        "estimator (estimator_node vergence_topic). Default: <namespace>/vergence when the bag has "
                        "it; '' = off")
    p.add_argument('--fixations', choices=FIXATION_CHOICES,
                   help="recorded = the bag's <namespace>/<side>/fixation messages (camera_node's); tracked = a "
                        'passive tracker on the images (for bags without them). Default: recorded when the bag has '
                        'both, else tracked')
    p.add_argument('--inputs', choices=INPUT_CHOICES,
                   help="images = the flow front end on the bag's images and joint states; observations = the "
                        "estimator alone on the bag's <namespace>/flow/observation (flow_node's output, e.g. fixego "
                        "demo's estimator_inputs/). Default: observations when the bag has them and no images")
    p.add_argument('--eval-out', type=Path, metavar='DIR',
                   help='with ground truth: also write DIR/ground_truth.tum, DIR/eval.json and DIR/eval.png')
    p.add_argument('--workers', type=int, choices=(1, 2), default=2 if (os.cpu_count() or 1) > 1 else 1,
                   help='2 = run the estimator in a second process (same output; default on multi-core machines)')
    p.add_argument('--no-progress', action='store_true', help='no progress bar on stderr')
    p.add_argument('--quiet', action='store_true', help='print only errors and the result lines')
    p.set_defaults(func=run)


def _pairs(items: list[str], what: str) -> list[tuple[str, str]]:
    out = []
    for item in items:
        a, sep, b = item.partition(':=')
        if not sep or not a or not b:
            raise ValueError(f'{what} {item!r}: expected NAME:=VALUE')
        out.append((a.strip(), b.strip()))
    return out


def settings_from_args(args: argparse.Namespace, rig):
    """ReplaySettings from the node tables, the parameter files and the options (later wins)."""

    from fixego_ros.pipeline.odometry import SPEED_PARAMS, SpeedSettings
    from fixego_ros.pipeline.params import (
        ESTIMATOR_PARAMS,
        FIXATION_PARAMS,
        FLOW_PARAMS,
        NODE_PARAMS,
        ParamsError,
        load_params_file,
        params_getter,
        parse_value,
    )
    from fixego_ros.replay.run import FixationSource, ReplayInput, ReplaySettings

    nodes = {'camera_node': FIXATION_PARAMS, 'flow_node': FLOW_PARAMS,
             'estimator_node': {**ESTIMATOR_PARAMS, **SPEED_PARAMS}}
    values: dict[str, dict[str, object]] = {n: {} for n in nodes}
    for f in args.params_file:
        for n in nodes:
            values[n].update(load_params_file(f, n))
    options = {'flow_node': {'preset': args.preset, 'keyframe_max_frames': args.keyframe_max_frames},
               'estimator_node': {'window': args.window, 'mode': args.mode, 'speed_topic': args.speed_topic,
                                  'speed_default_std': args.speed_default_std}}
    for n, kv in options.items():
        values[n].update({k: v for k, v in kv.items() if v is not None})
    for name, text in _pairs(args.param, '--param'):
        owners = [n for n, table in nodes.items() if name in table]
        if not owners:
            elsewhere = [n for n, table in NODE_PARAMS.items() if name in table]
            if elsewhere:    # a real node parameter that only means something to a live node
                hint = REPLAY_OPTION.get(name, 'it has no effect offline')
                raise ParamsError(f'parameter {name} of {elsewhere[0]} is not used by replay ({hint})')
            raise ParamsError(f'unknown parameter {name!r} (see config/camera_node.yaml, flow_node.yaml, '
                              f'estimator_node.yaml)')
        value = parse_value(name, text)
        for n in owners:     # fb_max_px exists for the fixation tracker and the flow: -p sets both
            values[n][name] = value
    getters = {n: params_getter(table, values[n]) for n, table in nodes.items()}
    return ReplaySettings.from_getters(rig, getters['camera_node'], getters['flow_node'], getters['estimator_node'],
                                       SpeedSettings.from_getter(getters['estimator_node']),
                                       vergence_topic=args.vergence_topic or '',
                                       fixations=FixationSource(args.fixations or FixationSource.TRACKED.value),
                                       inputs=ReplayInput(args.inputs or ReplayInput.IMAGES.value))


def run(args: argparse.Namespace) -> int:
    """``fixego replay``; see the module docstring for the exit codes."""
    bars: list = []          # the progress bar, so an interruption ends its line before saying so
    try:
        with signals_interrupt():
            return _run(args, bars)
    except KeyboardInterrupt as e:
        for bar in bars:
            bar.finish()
        signum = getattr(e, 'signum', signal.SIGINT)
        print(f'{PROG}: interrupted by {signal.Signals(signum).name}', file=sys.stderr, flush=True)
        return 128 + signum


def _run(args: argparse.Namespace, bars: list) -> int:
    import numpy as np

    from fixego_ros.bags.reader import Bag, BagError
    from fixego_ros.evaluation.tum import write_tum
    from fixego_ros.geometry.rig import SIDES, RigError, load_rig
    from fixego_ros.pipeline.params import ParamsError
    from fixego_ros.progress import Progress
    from fixego_ros.replay.run import (
        FixationSource,
        ReplayError,
        ReplayInput,
        ReplayTopics,
        bag_defaults,
        intrinsics_from_bag,
        replay,
    )

    def fail(msg: str) -> int:
        print(f'{PROG}: {msg}', file=sys.stderr)
        return 2

    def say(msg: str) -> None:
        if not args.quiet:
            print(msg)

    try:
        check_out_file(args.out)
        bag = Bag(args.bag)
    except (BagError, OptionError) as e:
        return fail(str(e))
    rig_path = args.rig or bag.dir / 'rig.yaml'
    if not rig_path.exists():
        return fail(f'no rig file: {rig_path} does not exist (pass --rig RIG.yaml; DESIGN.md §4)')
    try:
        rig = load_rig(rig_path)
        topics = ReplayTopics(args.namespace, tuple(_pairs(args.remap, '--remap')))
        rig, problems = intrinsics_from_bag(bag, rig, topics)     # what the rig file lacks; disagreements
        for problem in problems:
            print(f'{PROG}: error: {problem}', file=sys.stderr)
        defaults = bag_defaults(bag, topics)     # the bag's vergence measurements and fixations, when it has them
        image_options = [o for o, v in (('--preset', args.preset), ('--keyframe-max-frames', args.keyframe_max_frames),
                                        ('--fixations', args.fixations)) if v is not None]
        if args.vergence_topic is None:
            args.vergence_topic = defaults['vergence_topic']
        if args.fixations is None:
            args.fixations = defaults['fixations'].value
        if args.inputs is None:
            args.inputs = defaults['inputs'].value
        settings = settings_from_args(args, rig)
        if settings.speed.topic and not settings.speed.topic.startswith('/'):
            # a relative speed_topic (as the node takes it, in its namespace) names the bag topic under --namespace
            settings = dataclasses.replace(settings, speed=dataclasses.replace(
                settings.speed, topic=topics.name(settings.speed.topic)))
    except (RigError, ParamsError, ValueError, ReplayError, BagError) as e:
        return fail(str(e))
    observed = settings.inputs is ReplayInput.OBSERVATIONS
    if observed and image_options:
        return fail(f'{" and ".join(image_options)} act on the images, and this replay starts from the flow node\'s '
                    'observations (--inputs observations): leave them out, or replay a bag with images')
    counted = [topics.name('flow/observation')] if observed else [topics.name(f'{s}/image_raw') for s in SIDES]
    counts = [bag.topics[t].count for t in counted if t in bag.topics]
    bar = Progress(sum(c or 0 for c in counts), PROG, enabled=not (args.no_progress or args.quiet),
                   unit='observations' if observed else 'images')
    bars.append(bar)
    try:
        res = replay(bag, rig, settings, topics, progress=bar.update, workers=args.workers)
    except (ReplayError, BagError) as e:
        bar.finish()
        return fail(str(e))
    bar.finish()
    out: Path = args.out
    raw_out = out.with_name(out.name[:-4] + '.raw.tum' if out.name.endswith('.tum') else out.name + '.raw.tum')
    try:
        write_tum(out, res.stamps, res.poses)
        write_tum(raw_out, res.stamps, res.poses_raw)
    except OSError as e:
        return fail(f'cannot write {out}: {e}')

    for line in res.notes:
        if line != res.corrupt:          # said last, as the error it is
            print(f'{PROG}: note: {line}', file=sys.stderr)
    c = res.counts
    what = (f'{c["frames"]} observations (the estimator alone)' if observed else
            f'{c["images"]} images, {c["frames"]} frames ({c["stereo_frames"]} stereo)')
    say(f'replayed {bag.path}: {what}, {len(res.stamps)} poses over {res.bag_duration_s:.2f} s in {res.wall_s:.2f} s '
        f'({res.realtime_factor:.1f}x real time); steps: '
        + ', '.join(f'{k} {v}' for k, v in sorted(res.steps.items())))
    stages = ', '.join(f'{k} {np.median(v):.2f}' for k, v in res.stage_ms.items() if v)
    if observed:
        say(f'median ms per call: {stages}; fixations: those of the observations')
    else:
        fixations = ("the bag's messages" if settings.fixations is FixationSource.RECORDED
                     else 'tracked on the images')
        say(f'median ms per call: {stages}; fixations: {fixations}, re-selections right {c["reselections:right"]}, '
            f'left {c["reselections:left"]}')
    if settings.speed.topic:
        say(f'speed aid {settings.speed.topic}: {c["speed_samples"]} samples given to the estimator')
    if settings.vergence_topic:
        say(f'vergence {settings.vergence_topic}: {c["vergence"]} measurement(s) given to the estimator'
            + (f'; the right fixation re-selected at the measured point for {c["vergence_reselections"]} of them (it '
               'followed another point)' if c['vergence_reselections'] else ''))
    say(f'wrote {out} and {raw_out}')
    if res.gt_stamps:
        code = _evaluate(args, res, say, fail)
    else:
        say('no ground truth in the bag: no ATE')
        code = 0
    if res.corrupt:
        return fail(f'{bag.path}: {res.corrupt}; {out} holds the {len(res.stamps)} poses estimated before it')
    return code


def _evaluate(args: argparse.Namespace, res, say, fail) -> int:
    import numpy as np

    from fixego_ros.evaluation.cli import summary_lines
    from fixego_ros.evaluation.metrics import EvaluationError, evaluate
    from fixego_ros.evaluation.tum import write_tum

    try:
        evs = {name: evaluate(res.stamps, poses, res.gt_stamps, res.gt_poses, anchor_first=True, name=name)
               for name, poses in (('refined', res.poses), ('raw', res.poses_raw))}
    except EvaluationError as e:
        print(f'{PROG}: note: no ATE: {e}', file=sys.stderr)
        return 0
    for name, ev in evs.items():
        for line in summary_lines(name, ev.summary):
            print(line)
    if args.eval_out is not None:
        from fixego_ros.evaluation.plot import plot_evaluation
        d: Path = args.eval_out
        try:
            write_tum(d / 'ground_truth.tum', res.gt_stamps, res.gt_poses)
            (d / 'eval.json').write_text(json.dumps({k: ev.summary for k, ev in evs.items()}, indent=2,
                                                    allow_nan=False) + '\n')
            plot_evaluation(d / 'eval.png', evs, gt_stamps=np.asarray(res.gt_stamps),
                            gt_xyz=np.array([p.t for p in res.gt_poses]), title=args.bag.name)
        except OSError as e:
            return fail(f'cannot write to {d}: {e}')
        say(f'wrote {d / "ground_truth.tum"}, {d / "eval.json"} and {d / "eval.png"}')
    return 0
