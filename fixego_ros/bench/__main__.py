"""``make bench``: run every benchmark module, repeat, and write ``bench/results.json`` + ``bench/results.md``.

Each module in :data:`MODULES` has ``run() -> dict[str, float]``. Every figure is reported with its
median and spread (min, max) over ``--repeat`` runs. ``--only`` re-measures some modules and keeps the other
modules' figures from the existing ``results.json``; the table says when each module was measured.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

MODULES = ['fixego_ros.bench.core', 'fixego_ros.bench.flow', 'fixego_ros.bench.render', 'fixego_ros.bench.servo',
           'fixego_ros.bench.joints', 'fixego_ros.bench.replay', 'fixego_ros.bench.accuracy', 'fixego_ros.bench.seeds',
           'fixego_ros.bench.live']


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='python -m fixego_ros.bench')
    ap.add_argument('--out', default='bench')
    ap.add_argument('--repeat', type=int, default=3)
    ap.add_argument('--only', default='', help='comma-separated module suffixes, e.g. core,render')
    args = ap.parse_args(argv)
    only = {s.strip() for s in args.only.split(',') if s.strip()}
    runs: dict[str, list[float]] = {}
    reports = []
    for mod in MODULES:
        if only and mod.rsplit('.', 1)[-1] not in only:
            continue
        try:
            m = importlib.import_module(mod)
        except ImportError as e:
            print(f'skip {mod}: {e}')
            continue
        if hasattr(m, 'report'):
            reports.append(m)
        for _ in range(args.repeat):
            for k, v in m.run().items():
                if isinstance(v, (int, float)) and not isinstance(v, bool):   # labels are not figures
                    runs.setdefault(f'{mod.rsplit(".", 1)[-1]}.{k}', []).append(float(v))
    now = time.strftime('%Y-%m-%d %H:%M:%S')
    measured = {k: {'median': float(np.median(v)), 'min': float(np.min(v)), 'max': float(np.max(v)),
                    'runs': len(v), 'when': now} for k, v in runs.items()}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for m in reports:
        m.report(out)       # modules with tables and plots of their own (accuracy)
    results = _kept(out / 'results.json', {k.split('.', 1)[0] for k in measured}) if only else {}
    results.update(measured)
    results = {k: results[k] for k in sorted(results, key=_module_order)}
    meta = {'when': now, 'machine': platform.platform(), 'cpus': os.cpu_count(), 'repeat': args.repeat}
    (out / 'results.json').write_text(json.dumps({'meta': meta, 'results': results}, indent=1))
    lines = ['| figure | median | min | max | runs | measured |', '|---|---:|---:|---:|---:|---|']
    lines += [f'| {k} | {r["median"]:.3g} | {r["min"]:.3g} | {r["max"]:.3g} | {r["runs"]} | {r.get("when", "")} |'
              for k, r in results.items()]
    (out / 'results.md').write_text(f'# Benchmarks\n\n{meta}\n\n' + '\n'.join(lines) + '\n')
    print('\n'.join(lines))
    return 0


def _kept(path: Path, remeasured: set[str]) -> dict[str, dict]:
    """The figures of the modules not re-measured now, from an earlier ``results.json`` (each with the time it was
    measured: the file's own time for those written before figures carried one)."""
    if not path.exists():
        return {}
    old = json.loads(path.read_text())
    when = old.get('meta', {}).get('when', '')
    return {k: {'when': when, **r} for k, r in old.get('results', {}).items() if k.split('.', 1)[0] not in remeasured}


def _module_order(key: str) -> int:
    """Rows in :data:`MODULES` order (a module's own rows keep the order they were measured in)."""
    names = [m.rsplit('.', 1)[-1] for m in MODULES]
    module = key.split('.', 1)[0]
    return names.index(module) if module in names else len(names)


if __name__ == '__main__':
    raise SystemExit(main())
