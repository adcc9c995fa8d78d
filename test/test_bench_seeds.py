"""The seed benchmark's summary: the distribution and the goal count it reports (the replays are in ``make bench``)."""

from __future__ import annotations

import argparse

import pytest

from fixego_ros.bench.seeds import GOAL_MEAN_CM, GOAL_TERMINAL_CM, _seed_numbers, main, seed_list, summarise, table


def _seed(mean: float, terminal: float) -> dict[str, float]:
    return {'mean_error_cm': mean, 'terminal_error_cm': terminal, 'ate_sim3_cm': mean / 2, 'path_length_ratio': 1.0}


def test_summary_counts_only_seeds_within_both_goals():
    per_seed = [[_seed(GOAL_MEAN_CM, GOAL_TERMINAL_CM)],        # on both bounds: within
                [_seed(1.0, GOAL_TERMINAL_CM + 0.01)],          # terminal over
                [_seed(GOAL_MEAN_CM + 0.01, 1.0)],              # mean over
                [_seed(50.0, 150.0)]]
    res = summarise(dict(enumerate(per_seed)))
    assert res['within_goal'] == 1
    assert res['seeds'] == 4
    assert res['mean_error_cm.max'] == 50.0
    assert res['mean_error_cm.median'] == pytest.approx((GOAL_MEAN_CM + GOAL_MEAN_CM + 0.01) / 2)
    assert res['terminal_error_cm.mean'] == pytest.approx((GOAL_TERMINAL_CM * 2 + 0.01 + 1.0 + 150.0) / 4)
    assert res['seed3.terminal_error_cm'] == 150.0


def test_table_has_a_row_per_seed_and_the_statistics():
    res = summarise({0: [_seed(2.0, 3.0), _seed(2.5, 3.0)], 1: [_seed(8.0, 12.0), _seed(40.0, 90.0)]})
    rows = table(res).strip().splitlines()
    assert len(rows) == 2 + 2 + 3
    assert rows[2].startswith('| 0 (`bags/paper`\'s recipe) | 2.00 | 3.00 |') and rows[2].endswith('| 2.00–2.50 |')
    assert rows[3].endswith('| 8.00–40.00 **flips** |')
    assert rows[-1].startswith('| **max** | 8.00 | 12.00 |')


def test_the_draws_give_the_goal_count_range_and_the_seeds_that_flip():
    # the first draw is the unperturbed replay: the per-seed figures and the goal count are its own
    per_seed = [[_seed(2.0, 3.0), _seed(2.2, 3.5), _seed(3.0, 4.5)],      # within, within, terminal over
                [_seed(11.0, 17.0), _seed(58.0, 104.0), _seed(11.5, 16.0)],  # flips (x5.3)
                [_seed(3.0, 3.0), _seed(3.3, 3.9), _seed(2.9, 3.1)]]       # within in every draw
    res = summarise(dict(enumerate(per_seed)))
    assert res['within_goal'] == 2 and res['draws'] == 3
    assert (res['within_goal.draws_min'], res['within_goal.draws_max']) == (1, 2)
    assert res['unstable'] == 1
    assert res['seed1.mean_error_cm'] == 11.0
    assert (res['seed1.mean_error_cm.draws_min'], res['seed1.mean_error_cm.draws_max']) == (11.0, 58.0)
    assert res['mean_error_cm.max'] == 11.0          # the statistics are over the first draw


def test_a_subset_of_seeds_keeps_their_numbers():
    # --only 6,18,28: each row and figure under the seed's own number, the statistics over those three
    res = summarise({6: [_seed(1.0, 0.7)], 18: [_seed(8.3, 10.9)], 28: [_seed(2.0, 3.9)]})
    assert seed_list(res) == [6, 18, 28]
    assert res['seeds'] == 3 and res['within_goal'] == 2
    assert res['seed18.terminal_error_cm'] == 10.9 and 'seed0.mean_error_cm' not in res
    rows = table(res).strip().splitlines()
    assert [r.split('|')[1].strip() for r in rows[2:5]] == ['6', '18', '28']
    assert res['mean_error_cm.max'] == 8.3


def test_only_takes_distinct_non_negative_seed_numbers():
    assert _seed_numbers('28,6,18') == [28, 6, 18]
    for bad in ('6,,8', 'six', '-1', '6,6'):
        with pytest.raises(argparse.ArgumentTypeError):
            _seed_numbers(bad)


def test_keep_refuses_a_folder_that_has_a_seeds_bag_already(tmp_path, capsys):
    (tmp_path / 'paper_18').mkdir()
    with pytest.raises(SystemExit) as e:
        main(['--only', '6,18', '--keep', str(tmp_path), '--out', str(tmp_path / 'out')])
    assert e.value.code == 2
    assert 'seeds 18 exist already' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists() and not (tmp_path / 'paper_6').exists()     # nothing ran
