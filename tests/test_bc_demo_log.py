"""The PilotNet demo lap's log line gives mean |CTE| in metres, and names the paper's unit beside it (R6 finding 4:
a bare "2.9 units" is not SI and was not defined)."""

from __future__ import annotations

from train.bc import demo_cte_text


def test_demo_cte_is_in_metres_and_the_paper_unit_is_named():
    line = demo_cte_text({"cte_mean_abs_m": 0.1125, "cte_mean_abs_units": 2.93})
    assert line == "mean |CTE| 0.113 m (2.9 paper units, lane = 100)"
    assert "nan m" in demo_cte_text({})  # a lap without metrics says so, not 0
