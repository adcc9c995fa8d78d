"""``python -m fixego_ros.bench``: ``--only`` re-measures some modules and keeps the others' figures."""

from __future__ import annotations

import json
import sys
import types

from fixego_ros.bench import __main__ as bench


def _module(name: str, figures: dict[str, float]) -> str:
    mod = types.ModuleType(f'fake_bench.{name}')
    mod.run = lambda: dict(figures)
    sys.modules[mod.__name__] = mod
    return mod.__name__


def test_only_remeasures_its_modules_and_keeps_the_others_rows_with_when_they_were_measured(tmp_path, monkeypatch):
    monkeypatch.setattr(bench, 'MODULES', [_module('first', {'x_ms': 1.0}), _module('second', {'y_ms': 2.0})])
    assert bench.main(['--out', str(tmp_path), '--repeat', '2']) == 0
    before = json.loads((tmp_path / 'results.json').read_text())['results']
    assert set(before) == {'first.x_ms', 'second.y_ms'} and before['second.y_ms']['median'] == 2.0

    monkeypatch.setattr(bench, 'MODULES', [_module('first', {'x_ms': 1.0}), _module('second', {'y_ms': 5.0})])
    monkeypatch.setattr(bench.time, 'strftime', lambda fmt: 'later')
    assert bench.main(['--out', str(tmp_path), '--repeat', '1', '--only', 'second']) == 0
    after = json.loads((tmp_path / 'results.json').read_text())['results']
    assert list(after) == ['first.x_ms', 'second.y_ms']                    # the modules' order
    assert after['first.x_ms'] == before['first.x_ms']                     # kept as measured then
    assert after['second.y_ms']['median'] == 5.0 and after['second.y_ms']['when'] == 'later'
    table = (tmp_path / 'results.md').read_text()
    assert '| first.x_ms | 1 | 1 | 1 | 2 |' in table and '| second.y_ms | 5 | 5 | 5 | 1 | later |' in table

    assert bench.main(['--out', str(tmp_path), '--repeat', '1']) == 0      # a full run keeps nothing old
    assert all(r['when'] == 'later' for r in json.loads((tmp_path / 'results.json').read_text())['results'].values())
