"""train/operating_point.py's choice of a threshold from its validation table (``--rule``, ``--max-collision``)."""

from __future__ import annotations

import pytest

from av_gym.errors import ConfigError
from tests.test_nothing_lost import cli
from train.operating_point import choose

# (τ, collision, success) on the same validation episodes, shaped as a perceived student's sweep: success and
# collisions both fall as τ rises
SWEEP = [(0.5, 0.120, 0.800), (0.7, 0.060, 0.797), (0.8, 0.040, 0.790), (0.9, 0.026, 0.770), (0.95, 0.020, 0.730)]


def test_margin_takes_the_largest_success_minus_collision():
    assert choose(SWEEP, "margin")[0] == 0.8  # 0.750 against 0.737, 0.744, 0.710, 0.680


def test_capped_takes_the_largest_success_within_the_cap_not_the_largest_margin():
    """The truth student's 0.026 validation collisions as the cap: 0.8 (the margin's choice, 0.040) is over it, so
    0.9 (0.026, on the cap itself: a share typed as a decimal counts as equal) and not 0.95 (fewer collisions, less
    success)."""
    tau, why = choose(SWEEP, "capped", 0.026)
    assert tau == 0.9 and "0.770" in why
    assert choose(SWEEP, "capped", 0.04)[0] == 0.8
    assert choose(SWEEP, "capped", 1.0)[0] == 0.5


def test_capped_with_no_threshold_under_the_cap_takes_the_fewest_collisions():
    tau, why = choose(SWEEP, "capped", 0.01)
    assert tau == 0.95 and why.startswith("no threshold")


def test_ties_go_to_fewer_collisions_then_the_more_cautious_threshold():
    rows = [(0.7, 0.030, 0.800), (0.8, 0.020, 0.800), (0.9, 0.020, 0.800)]
    assert choose(rows, "capped", 0.03)[0] == 0.9
    # both 0.625 (binary fractions: an exact tie): the fewer collisions
    assert choose([(0.7, 0.25, 0.875), (0.8, 0.125, 0.75)], "margin")[0] == 0.8


def test_a_capped_rule_without_its_cap_is_refused():
    with pytest.raises(ConfigError, match="max_collision"):
        choose(SWEEP, "capped")
    with pytest.raises(ConfigError, match="rule must be one of"):
        choose(SWEEP, "largest")


@pytest.mark.parametrize("flags, says", [
    (["--rule", "capped"], "--max-collision goes with --rule capped"),
    (["--max-collision", "0.03"], "--max-collision goes with --rule capped"),
    (["--rule", "capped", "--max-collision", "1.5"], "argument --max-collision"),
    (["--rule", "best"], "argument --rule"),
])
def test_the_command_refuses_a_rule_without_its_cap_in_one_line_before_any_episode(flags, says, capsys):
    from train.operating_point import main

    line = cli(main, ["checkpoints/reference/dagger_turn", "--episodes", "1", *flags], capsys)
    assert line.startswith("error: ") and says in line, line
