"""The results page and the README's headline block are what the committed result files give."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest

from eval.results_page import BEGIN, END, load_all, main, page, quoted_block

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow  # every result folder's intervals (seeded bootstraps): ~19 s alone at load 2.3
def test_the_page_and_the_readme_block_are_what_the_result_files_give():
    """Fails when a result folder changed and the page was not regenerated, or README's numbers were typed."""
    text = page(load_all(ROOT / "docs" / "results"))
    assert (ROOT / "docs" / "results.md").read_text() == text, "run python -m eval.results_page --readme README.md"
    assert quoted_block((ROOT / "README.md").read_text(), "README.md") == quoted_block(text, "the page")
    assert "| test |" in quoted_block(text, "the page")  # the headline reports the test split


def _folder(root: Path, name: str, seeds, collisions, agent="always_proceed") -> Path:
    d = root / name
    d.mkdir(parents=True)
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["agent", "episode", "seed", "collision", "success", "min_ttc_s"])
        w.writeheader()
        for i, (s, c) in enumerate(zip(seeds, collisions)):
            w.writerow({"agent": agent, "episode": i, "seed": s, "collision": c, "success": 1 - c, "min_ttc_s": 0.0})
    (d / "meta.json").write_text(json.dumps({"command": "python -m eval env=left_turn split=test", "commit": "0" * 40,
                                             "started": "t0", "finished": "t1", "wall_s": 1, "load": "1"}))
    return d


def test_check_fails_when_a_result_or_the_readme_changes(tmp_path, capsys):
    results = tmp_path / "results"
    _folder(results, "lt", range(2_000_000, 2_000_020), [1] + [0] * 19)
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{BEGIN}\n{END}\nrest\n")
    args = ["--results", str(results), "--out", str(tmp_path / "results.md"), "--readme", str(readme)]
    assert main(args) == 0 and main([*args, "--check"]) == 0
    assert "0.050 [0.009, 0.236]" in readme.read_text() and readme.read_text().startswith("intro\n")
    assert "| 0 [0, 0] |" in (tmp_path / "results.md").read_text()  # an all-zero min TTC: a point, not [0, 0.79]
    readme.write_text(readme.read_text().replace("0.050 [0.009", "0.040 [0.009"))  # a number typed by hand
    assert main([*args, "--check"]) == 1 and "README.md differs" in capsys.readouterr().err
    main(args)
    shutil.rmtree(results / "lt")
    _folder(results, "lt", range(2_000_000, 2_000_020), [0] * 20)  # a result folder re-measured
    assert main([*args, "--check"]) == 1 and "results.md differs" in capsys.readouterr().err


@pytest.mark.parametrize("seeds, needle", [
    ([1_999_999, 2_000_000], "episodes from splits"),  # a validation seed in a test table
    ([2_000_000, 2_000_000], "same seed more than once"),  # one episode counted twice
])
def test_a_folder_mixing_splits_or_repeating_an_episode_is_refused(tmp_path, capsys, seeds, needle):
    _folder(tmp_path / "results", "lt", seeds, [0, 0])
    assert main(["--results", str(tmp_path / "results"), "--out", str(tmp_path / "p.md")]) == 2
    assert needle in capsys.readouterr().err


@pytest.mark.parametrize("missing", ["meta.json", "results.csv"])
def test_a_folder_without_its_meta_or_results_is_refused_in_one_line(missing, tmp_path, capsys):
    """A result folder whose meta.json is missing was skipped without a word: its rows (four headline rows for
    the folders of the issue) vanished from the page and the README's block. Refused, naming the folder."""
    results = tmp_path / "results"
    _folder(results, "kept", range(2_000_000, 2_000_004), [0, 0, 0, 0])
    (_folder(results, "lt", range(2_000_000, 2_000_004), [1, 0, 0, 0]) / missing).unlink()
    assert main(["--results", str(results), "--out", str(tmp_path / "p.md")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and f"{results / 'lt'} has no {missing}" in err[0], err
    assert not (tmp_path / "p.md").exists()


def test_a_folder_whose_meta_names_no_commit_is_refused_in_one_line(tmp_path, capsys):
    """eval writes commit null outside a git checkout (a snapshot, the wheel); a shipped folder names its code."""
    results = tmp_path / "results"
    meta = _folder(results, "lt", range(2_000_000, 2_000_004), [1, 0, 0, 0]) / "meta.json"
    meta.write_text(json.dumps({**json.loads(meta.read_text()), "commit": None}))
    assert main(["--results", str(results), "--out", str(tmp_path / "p.md")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and f"{meta}: commit is None" in err[0], err
    assert not (tmp_path / "p.md").exists()


def _seeds_folder(root: Path, name: str, collisions: dict[str, list[int]], first: int = 2_000_000) -> Path:
    """A result folder with several agents, each row its agent's collisions on test seeds ``first``, ``first+1``..."""
    d = root / name
    d.mkdir(parents=True)
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["agent", "episode", "seed", "collision", "success"])
        w.writeheader()
        for agent, cs in collisions.items():
            for i, c in enumerate(cs):
                w.writerow({"agent": agent, "episode": i, "seed": first + i, "collision": c, "success": 1 - c})
    (d / "meta.json").write_text(json.dumps({"command": "python -m eval env=left_turn split=test", "commit": "0" * 40,
                                             "started": "t0", "finished": "t1", "wall_s": 1, "load": "1"}))
    return d


SEED = "checkpoints/reference/seeds/ppo_turn/s{}"


def _rows(text: str, start: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip("|").split("|")] for line in text.splitlines() if line.startswith(start)]


def test_a_folder_with_training_seeds_gets_the_methods_lines_over_them(tmp_path):
    """Three seeds of ppo_turn (collision 0.1, 0.2, 0.6 on the same 10 episodes): every seed's row stays, and the
    method's mean (0.300) and IQM lines over 3 seeds follow them; the rule beside them is not grouped."""
    results = tmp_path / "results"
    _seeds_folder(results, "lt", {"always_proceed": [1] * 5 + [0] * 5, "ppo_turn": [1] + [0] * 9,
                                  SEED.format(2): [1] * 2 + [0] * 8, SEED.format(3): [1] * 6 + [0] * 4})
    text = page(load_all(results))
    section = text[text.index("## lt"):]
    agents = [r[0] for r in _rows(section, "| ")][2:]
    assert agents == ["always_proceed", "ppo_turn", SEED.format(2), SEED.format(3), "ppo_turn, mean of 3 seeds",
                      "ppo_turn, IQM of 3 seeds"]
    mean = _rows(section, "| ppo_turn, mean of 3 seeds")[0]
    assert mean[1:4] == ["3", "3 \u00d7 10", mean[3]] and mean[3].startswith("0.300 [")
    lo, hi = (float(v) for v in mean[3][len("0.300 ["):-1].split(", "))
    assert lo < 0.3 < hi and hi - lo > 0.2  # the seeds disagree: the interval says so
    assert _rows(section, "| ppo_turn, IQM of 3 seeds")[0][4].startswith("0.700 [")  # success, nothing cut at 3


def test_the_readme_block_says_which_rows_are_single_policies_and_which_are_over_seeds(tmp_path):
    results = tmp_path / "results"
    _seeds_folder(results, "lt", {"gap_acceptance": [0] * 4, "ppo_turn_shielded": [0] * 4, "ppo_turn+aeb": [0] * 4,
                                  SEED.format(2) + "+aeb": [1, 0, 0, 0], "dagger_turn": [0] * 4})
    block = quoted_block(page(load_all(results)), "the page")
    seeds = {r[0]: r[3] for r in _rows(block, "| ") if r[0] not in ("agent", "---")}
    assert seeds == {"gap_acceptance": "\u2013", "ppo_turn_shielded": "1", "ppo_turn+aeb": "1",
                     SEED.format(2) + "+aeb": "1", "dagger_turn": "1", "ppo_turn+aeb, mean of 2 seeds": "2",
                     "ppo_turn+aeb, IQM of 2 seeds": "2"}
    assert "1 is a single policy" in block and "stratified-bootstrap 95 % interval" in block
    assert "2000 resamples" in block


def test_seeds_of_one_method_on_different_episodes_are_refused_in_one_line(tmp_path, capsys):
    results = tmp_path / "results"
    d = _seeds_folder(results, "lt", {"ppo_turn": [0, 0, 1]})
    with open(d / "results.csv", "a", newline="") as f:
        csv.writer(f).writerows([[SEED.format(2), i, 2_000_010 + i, 0, 1] for i in range(3)])
    assert main(["--results", str(results), "--out", str(tmp_path / "p.md")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "training seeds of ppo_turn on different episodes" in err[0], err


def test_a_lane_keeping_folder_gets_pilotnets_line_over_seeds_for_its_metrics(tmp_path):
    """PilotNet and four extra training seeds on the same 20 test laps (each seed's |CTE| 0.04 + 0.01 k m, every
    lap completed): the method's lines give lane keeping's metrics over seeds; lap_completed, a rate where every
    lap ends alike, keeps the laps' chance (was 1.000 [1.000, 1.000], now the 100 laps' Wilson interval)."""
    results = tmp_path / "results"
    d = results / "lk"
    d.mkdir(parents=True)
    agents = ["pid_localized", "pilotnet", *(f"checkpoints/reference/seeds/pilotnet/s{k}" for k in range(1, 5))]
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["agent", "episode", "seed", "cte_mean_abs_m", "lap_completed"])
        w.writeheader()
        for k, agent in enumerate(agents):
            for i in range(20):
                w.writerow({"agent": agent, "episode": i, "seed": 2_000_000 + i,
                            "cte_mean_abs_m": 0.03 + 0.01 * k + 0.002 * (i % 5 - 2), "lap_completed": 1.0})
    (d / "meta.json").write_text(json.dumps({"command": "python -m eval env=lane_keeping env.track=B split=test",
                                             "commit": "0" * 40, "started": "t0", "finished": "t1", "wall_s": 1,
                                             "load": "1"}))
    text = page(load_all(results))
    mean = _rows(text[text.index("## lk"):], "| pilotnet, mean of 5 seeds")[0]
    assert mean[1:4] == ["5", "5 \u00d7 20", "1.000 [0.963, 1.000]"]
    assert mean[4].startswith("0.06 [")  # the seeds' means 0.04 .. 0.08
    lo, hi = (float(v) for v in mean[4][len("0.06 ["):-1].split(", "))
    assert 0.04 < lo < 0.06 < hi < 0.08
    headline = _rows(quoted_block(text, "the page"), "| pilotnet, IQM of 5 seeds")[0]
    assert headline[1:5] == ["lane keeping, layout B", "test", "5", "5 \u00d7 20"]


def test_seeds_driven_from_another_sensor_preset_are_their_own_method(tmp_path):
    """The truth student and its seed 2, each also driven from perceived features (``@turn_perceived``), in one
    folder: two methods of two seeds each, the preset's rows never averaged into the plain student's line."""
    results = tmp_path / "results"
    seed2 = "checkpoints/reference/seeds/dagger_turn/s2"
    _seeds_folder(results, "lt", {"dagger_turn": [0] * 4, seed2: [0] * 4, "dagger_turn@turn_perceived": [1] * 4,
                                  seed2 + "@turn_perceived": [1, 1, 0, 0]})
    section = page(load_all(results))
    section = section[section.index("## lt"):]
    assert _rows(section, "| dagger_turn, mean of 2 seeds")[0][3].startswith("0.000 [")
    assert _rows(section, "| dagger_turn@turn_perceived, mean of 2 seeds")[0][3].startswith("0.750 [")
    assert len(_rows(section, "| dagger_turn@turn_perceived, IQM of 2 seeds")) == 1
