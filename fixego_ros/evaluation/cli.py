"""``fixego eval EST.tum GT.tum``: ATE/RPE (evo) and the papers' drift measures, JSON + PNG (DESIGN.md §6)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from fixego_ros.cli_options import OptionError, check_float


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'eval', help='compare a TUM trajectory with ground truth (ATE/RPE, drift, plot)',
        description='Associate EST.tum with GT.tum by timestamp and report the papers\' measures (position '
                    'error per frame without alignment, terminal error, path-length ratio) and evo\'s APE '
                    '(unaligned, SE(3), Sim(3)) and RPE. Writes DIR/eval.json and DIR/eval.png.')
    p.add_argument('estimate', type=Path, metavar='EST.tum', help='estimated trajectory (refined)')
    p.add_argument('ground_truth', type=Path, metavar='GT.tum', help='ground-truth trajectory')
    p.add_argument('--raw', type=Path, metavar='RAW.tum', help='also evaluate and plot this (two-frame) trajectory')
    p.add_argument('--out', type=Path, metavar='DIR', help='output folder (default: the folder of EST.tum)')
    p.add_argument('--max-dt', type=float, default=None, metavar='S',
                   help='max. stamp difference for association in s (default 0.01)')
    p.add_argument('--anchor-first', action='store_true',
                   help='express both trajectories in their first associated pose before the unaligned '
                        'measures (when the estimate\'s odom is not the ground truth\'s)')
    p.add_argument('--rpe-delta-m', type=float, metavar='M', help='also report RPE over this travelled distance')
    p.add_argument('--title', help='figure title (default: the estimate file name)')
    p.set_defaults(func=run)


def _num(x: float | None, fmt: str, unit: str = '') -> str:
    """``x`` formatted (in powers of ten when huge: a diverged estimate), or 'n/a' when the summary has none
    (not computable, or beyond a float)."""
    if x is None:
        return 'n/a'
    return f'{x:{fmt if abs(x) < 1e9 else ".3e"}}{unit}'


def _cm(x: float | None) -> str:
    return _num(None if x is None else 100.0 * x, '.2f', ' cm')


def where_text(pe: dict[str, Any]) -> str:
    """Where a position error came from (``position_error_m``'s ``terminal_track`` and ``largest_growth``): the
    terminal error along the path (a scale lost) and across it (a heading lost), and the stretch where it grew."""
    track, growth = pe.get('terminal_track') or {}, pe.get('largest_growth') or {}
    along = track.get('along_m')
    sign = '+' if along is not None and along >= 0 else ''
    return (f'terminal along the path {sign}{_cm(along)}, across {_cm(track.get("across_m"))}; grew most from '
            f'{_num(growth.get("from_s"), ".1f", " s")} to {_num(growth.get("to_s"), ".1f", " s")} '
            f'(+{_cm(growth.get("growth_m"))})')


def summary_lines(name: str, s: dict[str, Any]) -> list[str]:
    """A short human summary of one evaluation summary dict (any number may be None: printed as n/a)."""
    pe, pl, ape, rpe = s['position_error_m'], s['path_length_m'], s['ape_translation_m'], s['rpe']
    sim3 = ape['sim3']
    scale = f' (scale {_num(sim3["scale"], ".3f")})' if 'scale' in sim3 else ''
    return [
        f'{name}: {s["poses"]["associated"]} of {s["poses"]["estimate"]} poses associated '
        f'({s["poses"]["ground_truth"]} in ground truth), {_num(s["duration_s"], ".2f", " s")}; '
        f'path {_num(pl["estimate"], ".3f", " m")} vs {_num(pl["ground_truth"], ".3f", " m")} '
        f'(ratio {_num(pl["ratio"], ".3f")})',
        f'  position error, no alignment: mean {_cm(pe["mean"])}, std {_cm(pe["std"])}, max {_cm(pe["max"])}, '
        f'terminal {_cm(pe["terminal"])}',
        f'  {where_text(pe)}',
        f'  ATE rmse: unaligned {_cm(ape["none"].get("rmse"))}, SE(3) {_cm(ape["se3"].get("rmse"))}, '
        f'Sim(3) {_cm(sim3.get("rmse"))}{scale}',
        f'  RPE rmse per frame: {_cm(rpe["translation_m"].get("rmse"))}, '
        f'{_num(rpe["rotation_deg"].get("rmse"), ".3f", " deg")}',
    ]


MAX_DT_MAX = 3600.0          # s: association tolerance beyond an hour associates nothing meaningful
RPE_DELTA_MAX_M = 1e6         # m


def run(args: argparse.Namespace) -> int:
    """``fixego eval``: exit 0, 2 when the input cannot be used, 130 on Ctrl-C (one line, no traceback)."""
    try:
        return _run(args)
    except KeyboardInterrupt:
        print('fixego eval: interrupted', file=sys.stderr)
        return 130


def _run(args: argparse.Namespace) -> int:
    import numpy as np

    from fixego_ros.evaluation.metrics import DEFAULT_MAX_DT, EvaluationError, evaluate
    from fixego_ros.evaluation.tum import TumError, read_tum

    def fail(msg: str) -> int:
        print(f'fixego eval: {msg}', file=sys.stderr)
        return 2

    max_dt = DEFAULT_MAX_DT if args.max_dt is None else args.max_dt
    try:
        check_float(max_dt, '--max-dt', 0.0, MAX_DT_MAX, unit='s')
        if args.rpe_delta_m is not None:
            check_float(args.rpe_delta_m, '--rpe-delta-m', 0.0, RPE_DELTA_MAX_M, lo_open=True, unit='m')
    except OptionError as e:
        return fail(str(e))
    out_dir: Path = args.out if args.out is not None else args.estimate.parent
    try:
        gt_stamps, gt_poses = read_tum(args.ground_truth)
        files = {'estimate': args.estimate}
        if args.raw is not None:
            files['raw'] = args.raw
        results = {}
        for key, path in files.items():
            stamps, poses = read_tum(path)
            results[key] = evaluate(stamps, poses, gt_stamps, gt_poses, max_dt=max_dt, anchor_first=args.anchor_first,
                                    rpe_delta_m=args.rpe_delta_m, name=path.name)
    except (TumError, EvaluationError) as e:
        return fail(str(e))

    report = {
        'files': {'estimate': str(args.estimate), 'ground_truth': str(args.ground_truth),
                  'raw': None if args.raw is None else str(args.raw)},
        'estimate': results['estimate'].summary,
        'raw': results['raw'].summary if 'raw' in results else None,
    }
    for key, ev in results.items():
        for line in summary_lines('raw' if key == 'raw' else 'estimate', ev.summary):
            print(line)

    from fixego_ros.evaluation.plot import plot_evaluation
    labels = {'estimate': 'refined' if 'raw' in results else 'estimate', 'raw': 'raw'}
    json_path, png_path = out_dir / 'eval.json', out_dir / 'eval.png'
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(report, indent=2, allow_nan=False) + '\n', encoding='utf-8')
        gt_xyz = np.array([p.t for p in gt_poses]) if gt_poses else None
        plot_evaluation(png_path, {labels[k]: ev for k, ev in results.items()}, gt_stamps=gt_stamps, gt_xyz=gt_xyz,
                        title=args.title or args.estimate.name)
    except OSError as e:
        return fail(f'cannot write results to {out_dir}: {e}')
    print(f'wrote {json_path} and {png_path}')
    return 0
