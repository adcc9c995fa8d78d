"""``fixego paper-sim`` end to end on a few trials: JSON and plots written, numbers sane."""

from __future__ import annotations

import json

from fixego_ros.cli import main


def test_paper_sim_writes_report_and_plots(tmp_path):
    out = tmp_path / 'ps'
    rc = main(['paper-sim', '--out', str(out), '--presets', 'dense', '--trials', '6', '--trials-seq', '2',
               '--jobs', '1'])
    assert rc == 0
    report = json.loads((out / 'report.json').read_text())
    res = report['presets']['dense']
    two = res['two_steps']
    assert two['trials'] == 6
    for key in ('raw', 'paper', 'joint'):
        assert two[key]['translation_error']['n'] == 6
        assert two[key]['rotation_error']['mean'] >= 0
    assert two['paper']['cost_never_increased'] and two['joint']['cost_never_increased']
    assert 0 < two['crb']['translation_error_rms'] < 1e6
    assert set(res['window']['translation_error_by_n']) == {str(n) for n in range(3, 11)}
    assert len(res['accumulation']['raw']['mean_position_error_per_step']) == 12   # frames 0..11
    assert res['accumulation']['raw']['mean_position_error_per_step'][0] == 0.0
    png = (out / 'paper_sim_dense.png').read_bytes()
    assert png[:8] == b'\x89PNG\r\n\x1a\n' and len(png) > 10_000


def test_paper_sim_rejects_unknown_preset(tmp_path, capsys):
    assert main(['paper-sim', '--out', str(tmp_path), '--presets', 'nope']) == 2
    assert 'unknown preset' in capsys.readouterr().err
