"""The seed benchmark's summary: the distribution and the goal count it reports (the replays are in ``make bench``)."""

from __future__ import annotations

import pytest

from fixego_ros.bench.seeds import GOAL_MEAN_CM, GOAL_TERMINAL_CM, summarise, table


def _seed(mean: float, terminal: float) -> dict[str, float]:
    return {'mean_error_cm': mean, 'terminal_error_cm': terminal, 'ate_sim3_cm': mean / 2, 'path_length_ratio': 1.0}


def test_summary_counts_only_seeds_within_both_goals():
    per_seed = [_seed(GOAL_MEAN_CM, GOAL_TERMINAL_CM),          # on both bounds: within
                _seed(1.0, GOAL_TERMINAL_CM + 0.01),            # terminal over
                _seed(GOAL_MEAN_CM + 0.01, 1.0),                # mean over
                _seed(50.0, 150.0)]
    res = summarise(per_seed)
    assert res['within_goal'] == 1
    assert res['seeds'] == 4
    assert res['mean_error_cm.max'] == 50.0
    assert res['mean_error_cm.median'] == pytest.approx((GOAL_MEAN_CM + GOAL_MEAN_CM + 0.01) / 2)
    assert res['terminal_error_cm.mean'] == pytest.approx((GOAL_TERMINAL_CM * 2 + 0.01 + 1.0 + 150.0) / 4)
    assert res['seed3.terminal_error_cm'] == 150.0


def test_table_has_a_row_per_seed_and_the_statistics():
    res = summarise([_seed(2.0, 3.0), _seed(8.0, 12.0)])
    rows = table(res).strip().splitlines()
    assert len(rows) == 2 + 2 + 3
    assert rows[2].startswith('| 0 (`bags/paper`) | 2.00 | 3.00 |')
    assert rows[-1].startswith('| **max** | 8.00 | 12.00 |')
