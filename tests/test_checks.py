"""The integer-argument check (nanostage.checks.int_arg) in the wording of each caller."""

from __future__ import annotations

import numpy as np
import pytest

from nanostage import ConfigError
from nanostage.checks import int_arg
from nanostage.cycles import MoveProfile, standard_test_cycle, step_cycle
from nanostage.studies.paper_campaigns import CampaignSettings


def test_default_wording() -> None:
    assert int_arg("n", np.int64(7), 1, 9) == 7
    assert type(int_arg("n", np.int64(7), 1, 9)) is int
    with pytest.raises(ConfigError) as info:
        int_arg("n", np.int64(10), 1, 9)
    assert str(info.value) == "n = 10 is invalid: expected an integer in [1, 9]"
    with pytest.raises(TypeError) as type_info:
        int_arg("n", True, 0, 9)
    assert str(type_info.value) == "n must be an int, not bool"
    with pytest.raises(TypeError, match=r"^n must be an int, not float$"):
        int_arg("n", 2.0, 0, 9)


def test_cycle_wording() -> None:
    with pytest.raises(ConfigError) as info:
        standard_test_cycle(
            travel_m=0.02,
            overrun_m=1e-3,
            dwell_s=0.05,
            move=MoveProfile(),
            sample_period_s=1e-3,
            seed=7,
            runs=1,
        )
    assert str(info.value) == "runs = 1 is outside [2, 10000]"
    with pytest.raises(TypeError) as type_info:
        step_cycle(step_m=1e-6, repeats=2.0, dwell_s=0.2, return_s=0.1, sample_period_s=1e-3)  # type: ignore[arg-type]
    assert str(type_info.value) == "repeats must be an integer, got 2.0"
    assert int_arg("r", np.int32(3), 2, 5, wording="outside") == 3


@pytest.mark.parametrize("bad", [0, "3", 3.0, np.int64(3), True])
def test_settings_wording(bad: object) -> None:
    # A settings field takes a Python int only (it is written to JSON as given).
    with pytest.raises(ConfigError) as info:
        CampaignSettings(n_trials=bad)  # type: ignore[arg-type]
    expected = f"CampaignSettings.n_trials = {bad!r} is invalid: expected an integer in [1, "
    assert str(info.value).startswith(expected)
    assert CampaignSettings(n_trials=3).n_trials == 3


def test_executor_arg_takes_none_or_anything_with_submit() -> None:
    from concurrent.futures import ThreadPoolExecutor

    from nanostage.checks import executor_arg

    executor_arg(None)
    with ThreadPoolExecutor(max_workers=1) as pool:
        executor_arg(pool)
    with pytest.raises(TypeError, match=r"^executor must have a submit method .* not dict$"):
        executor_arg({})
