"""benchmarks/belief_tracks_paired.py as a user runs it, on ``--rows`` files written the way
benchmarks/belief_tracks_sweep.py writes them (av_gym.atomic.csv_text of its episodes' rows): the exchanges, the exact
McNemar p (scipy's two-sided binomial test of the discordant pairs), the paired interval, and the refusal of files
whose seeds differ."""

from __future__ import annotations

import json
import runpy
import sys

import numpy as np
import pytest
from scipy.stats import binomtest

from av_gym.atomic import csv_text
from tests.documented_commands import ROOT

SCRIPT = ROOT / "benchmarks" / "belief_tracks_paired.py"
SEEDS = range(1_944_000, 1_944_200)


def _rows(path, collided: set[int], arrived: set[int], seeds=SEEDS) -> str:
    """A sweep's --rows file at ``path``: one row per seed, the EpisodeMetrics columns the sweep writes around the
    two the script reads."""
    rows = [{"seed": s, "collision": s in collided, "success": s in arrived, "length": 120, "time_to_goal": 9.5}
            for s in seeds]
    path.write_text(csv_text(rows))
    return str(path)


def _run(monkeypatch, *argv: str) -> None:
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *argv])
    runpy.run_path(str(SCRIPT), run_name="__main__")


@pytest.fixture
def clear_case(tmp_path):
    """Point a collides in 21 episodes (20 of them b survives), b in 2 (1 of them a survives); b arrives in 30
    episodes a does not, a in 2 b does not (arrivals and collisions on other seeds)."""
    seeds = np.array(SEEDS)
    rng = np.random.default_rng(7)
    order = rng.permutation(seeds).tolist()
    both, only_a, only_b = order[:1], order[1:21], order[21:22]
    arrive_common = set(order[22:142])
    arrive_only_b, arrive_only_a = set(order[142:172]), set(order[172:174])
    a = _rows(tmp_path / "a.csv", set(both + only_a), arrive_common | arrive_only_a)
    b = _rows(tmp_path / "b.csv", set(both + only_b), arrive_common | arrive_only_b)
    return a, b


def test_the_counts_the_exact_p_and_the_intervals_sign(clear_case, tmp_path, monkeypatch, capsys):
    a, b = clear_case
    out = tmp_path / "pair.json"
    _run(monkeypatch, a, b, "--out", str(out))
    line = capsys.readouterr().out.strip()
    printed, written = json.loads(line), json.loads(out.read_text())
    assert printed["episodes"] == written["episodes"] == 200
    assert written["collided"] == {"only_a": 20, "only_b": 1, "mcnemar_p": binomtest(20, 21, 0.5).pvalue}
    assert {k: written["arrived"][k] for k in ("only_a", "only_b")} == {"only_a": 2, "only_b": 30}
    assert written["arrived"]["mcnemar_p"] == binomtest(2, 32, 0.5).pvalue
    # printed to two significant figures, never rounded away: 20 against 1 is p 2.1e-05 (2.098e-05), not 0.0
    assert '"mcnemar_p": 2.1e-05' in line and printed["collided"]["mcnemar_p"] == 2.1e-05
    assert printed["arrived"]["mcnemar_p"] == float(f"{binomtest(2, 32, 0.5).pvalue:.2g}") > 0
    assert written["a"] == {"collision": 0.105, "success": 0.61, "s_minus_c": 0.505}
    assert written["b"] == {"collision": 0.01, "success": 0.75, "s_minus_c": 0.74}
    diff = written["b_minus_a_s_minus_c"]
    assert diff["mean"] == 0.235 and 0 < diff["lo"] < diff["mean"] < diff["hi"]  # b clearly better: the sign known


def test_an_existing_out_file_is_refused_and_kept(clear_case, tmp_path, monkeypatch, capsys):
    a, b = clear_case
    out = tmp_path / "pair.json"
    out.write_text("an earlier result\n")
    with pytest.raises(SystemExit) as end:
        _run(monkeypatch, a, b, "--out", str(out))
    err = capsys.readouterr()
    assert end.value.code == 2 and err.out == "" and "--out" in err.err and len(err.err.strip().splitlines()) == 1
    assert out.read_text() == "an earlier result\n"


def test_no_exchange_is_p_one(tmp_path, monkeypatch, capsys):
    same = _rows(tmp_path / "a.csv", {1_944_003}, set(SEEDS[10:]))
    again = _rows(tmp_path / "b.csv", {1_944_003}, set(SEEDS[10:]))
    _run(monkeypatch, same, again)
    result = json.loads(capsys.readouterr().out)
    assert result["collided"]["mcnemar_p"] == result["arrived"]["mcnemar_p"] == 1.0
    assert result["b_minus_a_s_minus_c"] == {"mean": 0.0, "lo": 0.0, "hi": 0.0}


def test_seeds_in_one_file_only_are_refused(tmp_path, monkeypatch, capsys):
    """Episodes without a pair make no paired test: one error line naming how many seeds each file lacks."""
    a = _rows(tmp_path / "a.csv", set(), set(SEEDS), SEEDS[:-3])  # lacks the last 3
    b = _rows(tmp_path / "b.csv", set(), set(SEEDS), SEEDS[2:])  # lacks the first 2
    with pytest.raises(SystemExit) as end:
        _run(monkeypatch, a, b)
    err = capsys.readouterr()
    assert end.value.code == 2 and err.out == "" and len(err.err.strip().splitlines()) == 1
    assert err.err.startswith("error: ") and f"{a} lacks 3 of" in err.err and f"{b} lacks 2 of" in err.err


def test_a_seed_twice_in_one_file_is_refused(tmp_path, monkeypatch, capsys):
    a = _rows(tmp_path / "a.csv", set(), set(), [*SEEDS, SEEDS[0]])
    b = _rows(tmp_path / "b.csv", set(), set())
    with pytest.raises(SystemExit) as end:
        _run(monkeypatch, a, b)
    err = capsys.readouterr().err
    assert end.value.code == 2 and err.startswith("error: ") and "1 seeds appear more than once" in err


def test_an_out_file_that_appears_after_the_check_is_kept(clear_case, tmp_path, monkeypatch, capsys):
    """Another run writes --out after the script checked it and before the script's write (here: the moment the
    temporary file is named): that file is kept whole, the script refuses in one line, and leaves no temporary
    file. (An os.replace into place overwrote it.) The result was printed first, whole: the line a free --out
    prints, never part of one."""
    import av_gym.atomic

    a, b = clear_case
    out = tmp_path / "pair.json"
    named = av_gym.atomic.temporary_name

    def raced(path):
        if path == out and not out.exists():
            out.write_text("another run's result\n")
        return named(path)

    monkeypatch.setattr(av_gym.atomic, "temporary_name", raced)
    with pytest.raises(SystemExit) as end:
        _run(monkeypatch, a, b, "--out", str(out))
    err = capsys.readouterr()
    assert end.value.code == 2 and len(err.err.strip().splitlines()) == 1, err
    assert "--out" in err.err and "exists" in err.err
    assert out.read_text() == "another run's result\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.csv", "pair.json"]
    monkeypatch.setattr(av_gym.atomic, "temporary_name", named)
    _run(monkeypatch, a, b, "--out", str(tmp_path / "free.json"))
    assert err.out == capsys.readouterr().out and json.loads(err.out)["episodes"] == 200


def test_a_print_cut_short_leaves_no_out_file(clear_case, tmp_path, monkeypatch):
    """The table is printed, and flushed, before --out is written: a print that fails (a closed pipe; a Ctrl-C there
    the same) leaves no file the user never saw the numbers of. (Written first, pair.json stayed; printed without
    the flush, the closed pipe showed only at exit, after the write.)"""

    class Closed:  # buffered, as a pipe's stdout is: the failure comes at the flush
        def write(self, text):
            return len(text)

        def flush(self):
            raise BrokenPipeError(32, "Broken pipe")

    a, b = clear_case
    monkeypatch.setattr(sys, "stdout", Closed())
    with pytest.raises(BrokenPipeError):
        _run(monkeypatch, a, b, "--out", str(tmp_path / "pair.json"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.csv"]
