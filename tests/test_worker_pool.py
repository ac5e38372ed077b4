"""eval.runner.WorkerPool.parts: the first part to fail is raised at once, not after the parts before it finish."""
import time

import pytest

from eval.runner import WorkerPool


def _nothing() -> None:
    pass


def _part(part: tuple) -> str:
    """A part that sleeps ``part[1]`` s, then fails when ``part[0]`` is 'fail'."""
    kind, seconds = part
    time.sleep(seconds)
    if kind == "fail":
        raise ValueError("part 2 failed")
    return kind


@pytest.mark.slow  # spawns two interpreters (~2-4 s)
def test_a_later_part_that_fails_is_raised_before_an_earlier_slow_part_ends():
    start = time.monotonic()
    with pytest.raises(ValueError, match="part 2 failed"):
        with WorkerPool(2, _nothing) as pool:
            pool.parts(_part, [("slow", 60.0), ("fail", 0.0)])
    assert time.monotonic() - start < 30.0  # in order, it would wait out the 60 s part first


@pytest.mark.slow
def test_parts_come_back_in_the_order_given():
    with WorkerPool(2, _nothing) as pool:
        assert pool.parts(_part, [("a", 0.5), ("b", 0.0)]) == ["a", "b"]
