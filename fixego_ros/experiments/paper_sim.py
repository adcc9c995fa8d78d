"""``fixego paper-sim``: the English paper's numerical experiments (§4.1), with a Cramér–Rao column.

1. Two steps, n = 3: rotation/translation error of the second step, two-frame ("comparison method")
   vs local BA (paper mode, and joint mode), mean ± std, Welch's test, BA cost before/after.
2. Ten steps: mean translation error vs the BA window n = 3..10.
3. Eleven steps, n = 3: accumulated position error per step, with and without the local BA.

Presets (:data:`fixego_ros.experiments.point_scene.PRESETS`): ``paper`` (3 flow points per camera in
20x20 px, 2 px noise), ``dense`` (100 points in 300x300 px, 0.1 px), and the Japanese version's
set-ups ``jp_2m``/``jp_10m``. Results go to ``report.json`` and one PNG per preset.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from fixego_ros.estimation.config import papers_config, papers_solver
from fixego_ros.estimation.crb import relative_bounds, two_frame_crb
from fixego_ros.estimation.estimator import Estimator
from fixego_ros.estimation.frames import FrameResult, fixations_of, step_pairs
from fixego_ros.experiments.point_scene import PRESETS, PointScene, SceneConfig, random_motion_sequence
from fixego_ros.geometry.rotation import rotation_error_paper, translation_error_paper

BA_MODES = ('paper', 'joint')


def estimator_for(scene: PointScene, cfg: SceneConfig, window: int, mode: str = 'paper') -> Estimator:
    """Estimator tuned to the preset's noise (sigma = pixel noise / focal length); no jump rejection
    beyond 4 step lengths, so the experiment measures the method rather than the safety net."""
    sigma = max(cfg.noise_px, 1e-3) / scene.rig.right.fx
    solver = papers_solver(sigma=sigma, prior_step=cfg.step_length)
    return Estimator(scene.rig, papers_config(window=window, mode=mode, solver=solver,
                                              max_step_translation=4.0 * cfg.step_length))


def _run(est: Estimator, obs: list) -> list[FrameResult]:
    return [est.update(o) for o in obs]


def summary(x: list[float] | np.ndarray) -> dict[str, float]:
    x = np.asarray(x, dtype=float)
    return {'mean': float(np.mean(x)), 'std': float(np.std(x, ddof=1)) if len(x) > 1 else 0.0,
            'median': float(np.median(x)), 'n': len(x)}


def welch(a: list[float], b: list[float]) -> float:
    """Two-sided p-value of Welch's t-test (unequal variances)."""
    if len(a) < 2 or len(b) < 2:
        return float('nan')
    return float(stats.ttest_ind(a, b, equal_var=False).pvalue)


def experiment_two_steps(cfg: SceneConfig, trials: int, seed: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    err: dict[str, dict[str, list[float]]] = {k: {'rot': [], 'trans': []} for k in ('raw', *BA_MODES)}
    cost: dict[str, dict[str, list[float]]] = {m: {'before': [], 'after': []} for m in BA_MODES}
    crb_rot, crb_trans, ok = [], [], 0
    for _ in range(trials):
        scene = PointScene(cfg, rng)
        steps = random_motion_sequence(cfg, 2, rng)
        _, obs, clean = scene.frames(steps)
        truth = steps[1]
        for mode in BA_MODES:
            res = _run(estimator_for(scene, cfg, 3, mode), obs)[2]
            if mode == BA_MODES[0]:
                err['raw']['rot'].append(rotation_error_paper(res.step_raw.R, truth.R))
                err['raw']['trans'].append(translation_error_paper(res.step_raw.t, truth.t))
                ok += int(res.status.usable)
            err[mode]['rot'].append(rotation_error_paper(res.step.R, truth.R))
            err[mode]['trans'].append(translation_error_paper(res.step.t, truth.t))
            if res.ba is not None:
                cost[mode]['before'].append(res.ba.cost_before)
                cost[mode]['after'].append(res.ba.cost_after)
        pairs = step_pairs(scene.rig, fixations_of(clean[1]), clean[2])
        sigma = max(cfg.noise_px, 1e-3) / scene.rig.right.fx
        rb, tb = relative_bounds(truth, two_frame_crb(truth, pairs, sigma))
        crb_rot.append(rb)
        crb_trans.append(tb)
    out: dict[str, Any] = {'trials': trials, 'usable_two_frame_steps': ok}
    for k, v in err.items():
        out[k] = {'rotation_error': summary(v['rot']), 'translation_error': summary(v['trans'])}
    for m in BA_MODES:
        out[m]['welch_p_translation_vs_raw'] = welch(err['raw']['trans'], err[m]['trans'])
        out[m]['welch_p_rotation_vs_raw'] = welch(err['raw']['rot'], err[m]['rot'])
        out[m]['cost_px2_before'] = summary(cost[m]['before']) if cost[m]['before'] else None
        out[m]['cost_px2_after'] = summary(cost[m]['after']) if cost[m]['after'] else None
        out[m]['cost_never_increased'] = bool(all(a <= b + 1e-12 for a, b in
                                                  zip(cost[m]['after'], cost[m]['before'], strict=True)))
    # RMS of the bound = what an efficient estimator's RMS error would be
    out['crb'] = {'rotation_error_rms': float(np.sqrt(np.mean(np.square(crb_rot)))),
                  'translation_error_rms': float(np.sqrt(np.mean(np.square(crb_trans)))),
                  'translation_error_median': float(np.median(crb_trans))}
    out['raw']['translation_error_rms'] = float(np.sqrt(np.mean(np.square(err['raw']['trans']))))
    return out


def experiment_window(cfg: SceneConfig, trials: int, seed: int, n_steps: int = 10,
                      windows: tuple[int, ...] = tuple(range(3, 11))) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    per_n: dict[int, list[float]] = {n: [] for n in windows}
    raw: list[float] = []
    for _ in range(trials):
        scene = PointScene(cfg, rng)
        steps = random_motion_sequence(cfg, n_steps, rng)
        _, obs, _ = scene.frames(steps)
        for n in windows:
            results = _run(estimator_for(scene, cfg, n, 'paper'), obs)
            errs = [translation_error_paper(r.step.t, s.t) for r, s in zip(results[1:], steps, strict=True)]
            per_n[n].append(float(np.mean(errs)))
            if n == windows[0]:
                raw.append(float(np.mean([translation_error_paper(r.step_raw.t, s.t)
                                          for r, s in zip(results[1:], steps, strict=True)])))
    return {'trials': trials, 'steps': n_steps, 'raw_translation_error': summary(raw),
            'translation_error_by_n': {str(n): summary(v) for n, v in per_n.items()}}


def experiment_accumulation(cfg: SceneConfig, trials: int, seed: int, n_steps: int = 11) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    acc: dict[str, list[list[float]]] = {k: [] for k in ('raw', *BA_MODES)}
    for _ in range(trials):
        scene = PointScene(cfg, rng)
        steps = random_motion_sequence(cfg, n_steps, rng)
        poses, obs, _ = scene.frames(steps)
        for mode in BA_MODES:
            results = _run(estimator_for(scene, cfg, 3, mode), obs)
            acc[mode].append([float(np.linalg.norm(r.pose.t - p.t)) for r, p in zip(results, poses, strict=True)])
            if mode == BA_MODES[0]:
                acc['raw'].append([float(np.linalg.norm(r.pose_raw.t - p.t))
                                   for r, p in zip(results, poses, strict=True)])
    out: dict[str, Any] = {'trials': trials, 'steps': n_steps, 'unit': 'scene units (baseline = 1 or metres)'}
    for k, v in acc.items():
        a = np.asarray(v)
        out[k] = {'mean_position_error_per_step': a.mean(axis=0).tolist(),
                  'median_position_error_per_step': np.median(a, axis=0).tolist(),
                  'terminal': summary(a[:, -1])}
    out['welch_p_terminal_paper_vs_raw'] = welch(np.asarray(acc['raw'])[:, -1].tolist(),
                                                 np.asarray(acc['paper'])[:, -1].tolist())
    return out


def run_preset(name: str, cfg: SceneConfig, trials: int, trials_seq: int, seed: int) -> dict[str, Any]:
    t0 = time.perf_counter()
    out = {'config': asdict(cfg),
           'two_steps': experiment_two_steps(cfg, trials, seed),
           'window': experiment_window(cfg, trials_seq, seed + 1),
           'accumulation': experiment_accumulation(cfg, trials_seq, seed + 2)}
    out['seconds'] = time.perf_counter() - t0
    return out


def plot_preset(name: str, res: dict[str, Any], path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    two = res['two_steps']
    labels = ['two-frame', 'BA paper', 'BA joint', 'CRB (RMS)']
    for j, key in enumerate(('rotation_error', 'translation_error')):
        vals = [two[k][key]['mean'] for k in ('raw', *BA_MODES)]
        errs = [two[k][key]['std'] for k in ('raw', *BA_MODES)]
        crb = two['crb'][key + '_rms']
        x = np.arange(4) + 5 * j
        ax[0].bar(x[:3], vals, yerr=errs, color=['0.4', 'tab:red', 'tab:orange'], capsize=3)
        ax[0].bar(x[3], crb, color='tab:blue')
    ax[0].set_xticks([1.5, 6.5], ['rotation', 'translation'])
    ax[0].set_yscale('log')
    ax[0].set_title('(1) two steps: relative error, mean ± std')
    ax[0].legend(handles=[plt.Rectangle((0, 0), 1, 1, color=c) for c in ('0.4', 'tab:red', 'tab:orange', 'tab:blue')],
                 labels=labels, fontsize=8)
    w = res['window']
    ns = list(w['translation_error_by_n'])
    ax[1].errorbar([int(n) for n in ns], [w['translation_error_by_n'][n]['mean'] for n in ns],
                   yerr=[w['translation_error_by_n'][n]['std'] for n in ns], marker='o', capsize=3, color='tab:red')
    ax[1].axhline(w['raw_translation_error']['mean'], color='0.4', ls='--', label='two-frame')
    ax[1].set_xlabel('frames n in the local BA')
    ax[1].set_ylabel('mean relative translation error')
    ax[1].set_title('(2) translation error vs n (10 steps)')
    ax[1].legend(fontsize=8)
    acc = res['accumulation']
    for k, c in (('raw', '0.2'), ('paper', 'tab:red'), ('joint', 'tab:orange')):
        ax[2].plot(acc[k]['mean_position_error_per_step'], marker='.', color=c,
                   label={'raw': 'two-frame', 'paper': 'BA paper', 'joint': 'BA joint'}[k])
    ax[2].set_xlabel('step')
    ax[2].set_ylabel('mean accumulated position error')
    ax[2].set_title('(3) accumulation, n = 3')
    ax[2].legend(fontsize=8)
    fig.suptitle(f'paper-sim preset {name!r}')
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _job(args: tuple[str, int, int, int]) -> tuple[str, dict[str, Any]]:
    name, trials, trials_seq, seed = args
    return name, run_preset(name, PRESETS[name], trials, trials_seq, seed)


PROG = 'fixego paper-sim'
TRIALS_MAX = 1_000_000
JOBS_MAX = 64          # processes: one per preset is all that can run at once anyway
SEED_MAX = 2**32 - 1


def check_args(args: argparse.Namespace) -> list[str]:
    """Every option, before any work: the preset names; raises OptionError (one line naming the option)."""
    from fixego_ros.cli_options import OptionError, check_int
    names = [n.strip() for n in args.presets.split(',')]
    if not args.presets.strip() or not any(names):
        raise OptionError(f'--presets must name at least one preset of {", ".join(PRESETS)}, got {args.presets!r}')
    if '' in names:
        raise OptionError(f'--presets {args.presets!r}: an empty name (stray comma); known: {", ".join(PRESETS)}')
    bad = [n for n in names if n not in PRESETS]
    if bad:
        raise OptionError(f'--presets: unknown preset(s) {", ".join(map(repr, bad))}; known: {", ".join(PRESETS)}')
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise OptionError(f'--presets {args.presets!r}: {", ".join(twice)} given more than once')
    check_int(args.trials, '--trials', 2, TRIALS_MAX, note=" (two-step trials; Welch's test needs two)")
    check_int(args.trials_seq, '--trials-seq', 2, TRIALS_MAX, note=" (sequence trials; Welch's test needs two)")
    check_int(args.seed, '--seed', 0, SEED_MAX)
    check_int(args.jobs, '--jobs', 1, JOBS_MAX, note=' (parallel processes)')
    if not args.out or not args.out.strip():
        raise OptionError('--out must name an output directory, got an empty path')
    return names


def main(args: argparse.Namespace) -> int:
    """``fixego paper-sim``: exit code 0 done; 2 an option cannot be used (one ``fixego paper-sim: ...`` line on
    stderr before any work; nothing created), or the report cannot be written."""
    import sys

    from fixego_ros.cli_options import OptionError, prepare_out_dir
    try:
        names = check_args(args)
        out = prepare_out_dir(args.out, '--out')      # last: creates the folder
    except OptionError as e:
        print(f'{PROG}: {e}', file=sys.stderr)
        return 2
    jobs = [(n, args.trials, args.trials_seq, args.seed) for n in names]
    report: dict[str, Any] = {'seed': args.seed, 'presets': {}}
    if args.jobs > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(max_workers=min(args.jobs, len(jobs))) as pool:
            results = list(pool.map(_job, jobs))
    else:
        results = [_job(j) for j in jobs]
    try:
        for name, res in results:
            report['presets'][name] = res
            plot_preset(name, res, out / f'paper_sim_{name}.png')
            two = res['two_steps']
            te = {k: two[k]['translation_error'] for k in ('raw', *BA_MODES)}
            re_ = {k: two[k]['rotation_error'] for k in ('raw', *BA_MODES)}
            print(f'[{name}] translation error: two-frame {te["raw"]["mean"]:.3g} ± {te["raw"]["std"]:.3g} '
                  f'(CRB RMS {two["crb"]["translation_error_rms"]:.3g}), BA paper {te["paper"]["mean"]:.3g}, '
                  f'joint {te["joint"]["mean"]:.3g}; rotation error: two-frame {re_["raw"]["mean"]:.3g}, '
                  f'BA paper {re_["paper"]["mean"]:.3g}, joint {re_["joint"]["mean"]:.3g} ({res["seconds"]:.0f} s)')
        (out / 'report.json').write_text(json.dumps(report, indent=1))
    except OSError as e:
        print(f'{PROG}: cannot write to {out}: {e.strerror or e}', file=sys.stderr)
        return 2
    print(f'wrote {out / "report.json"} and {len(results)} plot(s)')
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    from fixego_ros.cli_options import one_line_errors
    p = sub.add_parser('paper-sim', help="the papers' numerical experiments (§4.1): JSON + plots",
                       description="The papers' numerical experiments (§4.1): report.json and one PNG per preset. "
                                   'Every option is checked before any work (exit code 2, one line).')
    p.add_argument('--out', default='paper_sim', help='output folder (report.json, PNGs; created or reused)')
    p.add_argument('--presets', default='paper,dense,jp_2m,jp_10m', help='comma-separated: ' + ','.join(PRESETS))
    p.add_argument('--trials', type=int, default=200, help=f'trials of experiment 1 (two steps), 2..{TRIALS_MAX}')
    p.add_argument('--trials-seq', type=int, default=30,
                   help=f'trials of experiments 2 and 3 (sequences), 2..{TRIALS_MAX}')
    p.add_argument('--seed', type=int, default=0, help=f'0..{SEED_MAX} (default 0)')
    p.add_argument('--jobs', type=int, default=2, help=f'presets run in parallel processes, 1..{JOBS_MAX} (default 2)')
    one_line_errors(p)
    p.set_defaults(func=main)
