"""docs/tradeoff_test.png is what its documented command draws from shipped rows, on the one seed set the text names
(R7, finding 6: the command globbed ~60 folders of three seed sets; the shipped figure had 17 points, its lookahead
0.007 / 0.908 matching no shipped row). docs/usage.md's paragraph names the inputs, the seeds and some numbers;
docs/tradeoff_test.points.csv is what the figure drew, and the PNG's metadata holds that file's sha256. Each check
here reads the rows itself (csv, no eval.tradeoff) so a fault of the tool cannot agree with itself. Also the tool's
refusals of rows of one agent given twice and of mixed seed sets."""

from __future__ import annotations

import csv
import hashlib
import re
import shlex
from collections import defaultdict
from pathlib import Path

import pytest

from tests.test_side_tools_keep_files import _tradeoff  # python -m eval.tradeoff in this process: (exit code, stderr)

ROOT = Path(__file__).resolve().parents[1]
FIGURE = ROOT / "docs" / "tradeoff_test.png"
POINTS = ROOT / "docs" / "tradeoff_test.points.csv"


def _paragraph() -> str:
    """docs/usage.md's trade-off paragraph, joined into one line."""
    text = (ROOT / "docs" / "usage.md").read_text()
    start = text.index("Trade-off plot on the test split")
    return " ".join(text[start:text.index("\n\n", start)].split())


def _command() -> list[str]:
    out = re.escape(str(FIGURE.relative_to(ROOT)))
    found = re.findall(rf"`(python -m eval\.tradeoff [^`]*--out {out}[^`]*)`", _paragraph())
    assert len(found) == 1, found
    return shlex.split(found[0])


def _inputs() -> list[str]:
    args = _command()[3:]
    return args[:next(i for i, a in enumerate(args) if a.startswith("--"))]


def _claimed_seeds() -> range:
    m = re.search(r"seeds (\d{1,3}(?:,\d{3})*)-(\d{1,3}(?:,\d{3})*), the same 1,000 seeds for every point",
                  _paragraph())
    assert m, "the paragraph no longer names the figure's seeds"
    first, last = (int(x.replace(",", "")) for x in m.groups())
    return range(first, last + 1)


def _named_rows() -> dict[str, list[dict]]:
    """label -> its rows in the documented inputs (named agents only, as ``--named-only`` draws)."""
    by_label: dict[str, list[dict]] = defaultdict(list)
    for path in _inputs():
        with open(ROOT / path, newline="") as f:
            for r in csv.DictReader(f):
                if "/" not in r["agent"]:
                    by_label[r["agent"]].append({**r, "_file": path})
    return by_label


def _shipped_points() -> dict[str, dict]:
    with open(POINTS, newline="") as f:
        return {r["label"]: r for r in csv.DictReader(f)}


def test_documented_inputs_exist_and_are_the_claimed_seed_set():
    """Every file the command names is shipped; every agent drawn from them is on exactly the seeds the text says,
    each seed once (one evaluation per agent: no folder named twice, no duplicate run in two folders)."""
    assert "--named-only" in _command() and "--overwrite" in _command()
    missing = [p for p in _inputs() if not (ROOT / p).is_file()]
    assert not missing, missing
    seeds = _claimed_seeds()
    assert seeds.start >= 2_000_000 and len(seeds) == 1000  # the test split's, as the text says
    by_label = _named_rows()
    assert len(by_label) >= 5
    for label, rows in by_label.items():
        got = sorted(int(r["seed"]) for r in rows)
        assert got == list(seeds), (label, len(got), got[:1], got[-1:], sorted({r["_file"] for r in rows}))


def test_shipped_points_are_the_named_rows():
    """docs/tradeoff_test.points.csv: one point per named agent and rule threshold of the inputs, each its rows'
    collision and success rate over n episodes, its seeds the claimed ones and its files the ones it came from."""
    shipped = _shipped_points()
    by_label = _named_rows()
    assert set(shipped) == set(by_label)
    seeds = _claimed_seeds()
    for label, rows in by_label.items():
        point = shipped[label]
        n = len(rows)
        assert int(point["n"]) == n, label
        assert float(point["collision"]) == pytest.approx(sum(float(r["collision"]) for r in rows) / n, abs=1e-12)
        assert float(point["success"]) == pytest.approx(sum(float(r["success"]) for r in rows) / n, abs=1e-12)
        assert float(point["collision_lo"]) <= float(point["collision"]) <= float(point["collision_hi"])
        assert (int(point["seed_first"]), int(point["seed_last"])) == (seeds.start, seeds.stop - 1), label
        assert point["files"].split(";") == list(dict.fromkeys(r["_file"] for r in rows)), label
    text = _paragraph()
    assert f"one point for each of the {sum('t_gap=' not in k for k in shipped)} named left-turn agents" in text
    assert f"swept over `t_gap` ({sum('t_gap=' in k for k in shipped)} points)" in text


def test_shipped_png_was_drawn_from_the_shipped_points():
    """The figure's metadata names the sha256 of the points file written with it: a figure redrawn from other rows
    (or points edited by hand) no longer matches."""
    from PIL import Image

    with Image.open(FIGURE) as image:
        description = image.text.get("Description", "")
    assert description == f"points.csv sha256 {hashlib.sha256(POINTS.read_bytes()).hexdigest()}"


def test_numbers_in_the_text_are_the_figure_points():
    """Each "`label` collision / success" the paragraph quotes is that point of the figure, to three decimals."""
    shipped = _shipped_points()
    quoted = re.findall(r"`([^`]+)` (\d\.\d{3}) / (\d\.\d{3})", _paragraph())
    assert len(quoted) >= 5, quoted
    for label, c, s in quoted:
        assert label in shipped, label
        assert (f"{float(shipped[label]['collision']):.3f}", f"{float(shipped[label]['success']):.3f}") == (c, s)


@pytest.mark.slow
def test_documented_command_redraws_the_shipped_points(tmp_path, monkeypatch, capsys):
    """The documented command itself (``--out`` in a temporary folder) writes the shipped points byte for byte and
    a PNG whose metadata names them."""
    from PIL import Image

    from eval.tradeoff import main

    argv = _command()[3:]
    at = argv.index("--out")
    argv[at + 1] = str(tmp_path / "t.png")
    monkeypatch.chdir(ROOT)
    main(argv)
    assert (tmp_path / "t.points.csv").read_bytes() == POINTS.read_bytes()
    with Image.open(tmp_path / "t.png") as image:
        assert image.text["Description"].endswith(hashlib.sha256(POINTS.read_bytes()).hexdigest())


# ------------------------------------------------------------------------ the tool's refusals
def _rows(path: Path, agent: str, seeds: range) -> Path:
    path.write_text("agent,seed,collision,success\n" + "".join(f"{agent},{s},0,1\n" for s in seeds))
    return path


def test_the_same_run_named_twice_is_refused(tmp_path, capsys):
    """The old documented glob named ppo_turn's run in two folders: its points were drawn over 2,000 rows."""
    a = _rows(tmp_path / "a.csv", "ppo_turn", range(10))
    b = _rows(tmp_path / "b.csv", "ppo_turn", range(10))
    code, err = _tradeoff([str(a), str(b), "--out", str(tmp_path / "t.png")], capsys)
    assert code == 2 and f"ppo_turn has seed 0 twice (in {a} and {b})" in err, err
    assert err.count("\n") == 1 and not list(tmp_path.glob("t.*"))


def test_agents_on_other_seeds_are_refused_unless_mixed_seeds(tmp_path, capsys):
    a = _rows(tmp_path / "a.csv", "lookahead", range(2_800_000, 2_800_010))
    b = _rows(tmp_path / "b.csv", "ppo_turn", range(2_000_000, 2_000_010))
    code, err = _tradeoff([str(a), str(b), "--out", str(tmp_path / "t.png")], capsys)
    assert code == 2 and "ppo_turn (10 seeds 2000000-2000009" in err and "name results of one seed set" in err, err
    assert not list(tmp_path.glob("t.*"))
    code, err = _tradeoff([str(a), str(b), "--out", str(tmp_path / "t.png"), "--mixed-seeds"], capsys)
    assert code == 0 and (tmp_path / "t.png").is_file() and (tmp_path / "t.points.csv").is_file(), err


def test_a_rule_sweep_on_other_seeds_than_the_rows_is_refused_before_it_plays(tmp_path, capsys, monkeypatch):
    import eval.tradeoff

    monkeypatch.setattr(eval.tradeoff, "rule_sweep", lambda *a: pytest.fail("the sweep ran"))
    a = _rows(tmp_path / "a.csv", "ppo_turn", range(2_000_000, 2_000_010))
    code, err = _tradeoff([str(a), "--out", str(tmp_path / "t.png"), "--rule-sweep", "2", "--episodes", "10",
                           "--seed", "1000000"], capsys)
    assert code == 2 and "the rule sweep would play --episodes 10 from --seed 1000000" in err, err


def test_named_only_leaves_out_checkpoints_given_by_path(tmp_path, capsys):
    a = tmp_path / "a.csv"
    a.write_text("agent,seed,collision,success\nppo_turn,0,0,1\ncheckpoints/reference/seeds/ppo_turn/s2,0,1,0\n")
    assert _tradeoff([str(a), "--out", str(tmp_path / "t.png"), "--named-only"], capsys)[0] == 0
    with open(tmp_path / "t.points.csv", newline="") as f:
        assert [r["label"] for r in csv.DictReader(f)] == ["ppo_turn"]
