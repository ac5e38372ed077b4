"""conf/cli.py: the side tools' argparse types say in one line what a flag takes, for one value as for a list."""

from __future__ import annotations

import argparse

import pytest

from conf.cli import ToolParser, items, number


@pytest.mark.parametrize("kind, low, high, text, says", [
    (int, 1, 64, "0", "expected an integer in [1, 64], got '0'"),
    (int, 1, 64, "abc", "expected an integer in [1, 64], got 'abc'"),
    (int, 1, 64, "2,3", "expected one value (an integer in [1, 64]), got '2,3'"),
    (int, 1, None, "0", "expected an integer >= 1, got '0'"),
    (int, None, None, "", "expected an integer, got ''"),
    (float, 0.1, 600.0, "nan", "expected a number in [0.1, 600.0], got 'nan'"),
    (float, 0.0, 1.0, "1.5", "expected a number in [0.0, 1.0], got '1.5'"),
])
def test_a_single_value_flag_says_what_one_value_may_be(kind, low, high, text, says):
    """A single value's message read as a list's ("each value must be in [1, None]", "expected a list of integers
    like [1,2], got 'abc' in 'abc'"): it now names one value, its type and its range (None bounds left out)."""
    with pytest.raises(argparse.ArgumentTypeError) as err:
        number(kind, low=low, high=high)(text)
    assert str(err.value) == says


def test_a_list_flag_names_the_item_and_leaves_out_an_open_bound():
    with pytest.raises(argparse.ArgumentTypeError) as err:
        items(int, low=1)("[4,0]")
    assert str(err.value) == "each value must be >= 1, got '0'"
    with pytest.raises(argparse.ArgumentTypeError) as err:
        items(float, low=0.0, high=1.0)("0.5,x")
    assert str(err.value) == "expected a list of numbers like [1,2], got 'x' in '0.5,x'"
    assert items(int, low=1)("[1, 2]") == [1, 2] and number(float, low=0.0)(" 2.5 ") == 2.5


def test_a_tool_refuses_a_bad_single_value_in_one_error_line(capsys):
    parser = ToolParser(prog="tool")
    parser.add_argument("--workers", type=number(int, low=1, high=64), default=1)
    with pytest.raises(SystemExit) as exit_:
        parser.parse_args(["--workers", "0"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err == "error: tool: argument --workers: expected an integer in [1, 64], got '0'\n"
