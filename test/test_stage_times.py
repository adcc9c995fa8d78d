"""StageTimes: where one back-end update's time goes (issue 19)."""

from __future__ import annotations

import time

import pytest

from fixego_ros.estimation.stage_times import Stage, StageTimes


def test_a_stage_entered_twice_adds_up_and_clear_starts_again():
    times = StageTimes()
    for _ in range(2):
        with times(Stage.ELIMINATE):
            time.sleep(0.002)
    out = times.as_dict()
    assert list(out) == [s.value for s in Stage]          # every stage, in the order they run
    assert out['eliminate'] >= 4.0 and out['linearise'] == 0.0
    times.clear()
    assert set(times.as_dict().values()) == {0.0}


def test_a_stage_that_raises_is_still_timed():
    times = StageTimes()
    with pytest.raises(RuntimeError), times(Stage.ELIMINATE):
        time.sleep(0.001)
        raise RuntimeError('indeterminate linear system')
    assert times.as_dict()['eliminate'] >= 1.0
