"""``python -m eval`` writes meta.json beside results.csv and results.md (eval/meta.py): the shipped result
folders' keys, the settings that chose the episodes, the exit status also on Ctrl-C and on a failure, and never
over a meta.json a person wrote."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import sys
import tarfile
from datetime import datetime

import pytest

from eval.meta import WRITTEN_BY, EvalMeta, archived_commit, code_commit, hand_written_problem

SHIPPED_KEYS = ["command", "commit", "started", "finished", "wall_s", "load", "rc"]  # docs/results/*/meta.json
ARGV = ["agents=[always_proceed,gap_acceptance]", "split=validation", "episodes=2", "out_dir=out",
        "progress_bar=false", "hydra.run.dir=hydra"]


def _eval(tmp_path, monkeypatch, fails_with=None, argv=ARGV, midway: list | None = None):
    """``python -m eval`` with ``argv`` in ``tmp_path``, each agent's episodes one stand-in row per seed (the
    meta.json is about the run, not the episodes); the second agent, when ``fails_with`` is given, appending
    the meta.json it finds (the first agent's) to ``midway``, finishing one episode and raising ``fails_with``."""
    from eval import __main__ as eval_main

    def row(plan, i: int, seed: int) -> dict:
        return {"agent": plan.label, "episode": i, "seed": seed, "collision": 0.0, "success": 1.0}

    def run_agent(plan, command, env_cfg, seeds, rows) -> None:
        if rows and fails_with is not None:
            if midway is not None:
                midway.append(json.loads((tmp_path / "out" / "meta.json").read_text()))
            rows.append(row(plan, 0, seeds[0]))  # one episode of the second agent finished, then it stops
            raise fails_with("stopped")
        rows += [row(plan, i, s) for i, s in enumerate(seeds)]

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(eval_main, "_run_agent", run_agent)
    monkeypatch.setattr(sys, "argv", ["eval", *argv])
    if fails_with is None:
        eval_main.main()
    else:
        with pytest.raises((fails_with, SystemExit)):
            eval_main.main()
    return tmp_path / "out"


def test_eval_writes_meta_json_with_the_shipped_keys_and_what_ran(tmp_path, monkeypatch):
    out = _eval(tmp_path, monkeypatch)
    meta = json.loads((out / "meta.json").read_text())
    assert list(meta)[:len(SHIPPED_KEYS)] == SHIPPED_KEYS
    assert meta["command"] == "python -m eval " + " ".join(ARGV)
    assert meta["commit"] == code_commit() and (meta["commit"] is None or len(meta["commit"]) == 40)
    started, finished = (datetime.strptime(meta[k], "%Y-%m-%dT%H:%M:%SZ") for k in ("started", "finished"))
    assert started <= finished and 0 <= meta["wall_s"] <= (finished - started).total_seconds() + 1
    lo, hi = (float(x) for x in meta["load"].split("-"))
    assert lo >= 0 and hi >= 0
    assert meta["rc"] == 0 and meta["episodes_written"] == 4 and meta["cpu_s"] >= 0
    assert (meta["split"], meta["episodes"], meta["agents"]) == ("validation", 2, ["always_proceed", "gap_acceptance"])
    assert meta["seeds"] == [1_000_000, 1_000_001]  # the validation split's first two (av_gym/seeds.py)
    assert (meta["vec_env"], meta["n_envs"], meta["workers"]) == ("subproc", 1, 1)  # EvalCommand's defaults
    assert meta["versions"]["python"] == ".".join(map(str, sys.version_info[:3]))
    assert set(meta["versions"]) >= {"numpy", "torch", "highway-env"} and meta["written_by"] == WRITTEN_BY
    assert sorted(p.name for p in out.iterdir()) == ["meta.json", "results.csv", "results.md"]


@pytest.mark.parametrize(("fails_with", "rc"), [(KeyboardInterrupt, 130), (RuntimeError, 1)])
def test_an_interrupted_or_failing_eval_says_its_exit_status_and_the_rows_it_kept(fails_with, rc, tmp_path,
                                                                                 monkeypatch):
    """Ctrl-C keeps (writes) the second agent's finished episode, a failure only the first agent's rows: meta.json
    counts the rows results.csv holds either way."""
    midway = []
    out = _eval(tmp_path, monkeypatch, fails_with, midway=midway)
    # what a kill -9 during the second agent leaves: the first agent's rows counted, rc null, not finished
    assert [(m["rc"], m["finished"], m["episodes_written"]) for m in midway] == [(None, None, 2)]
    meta = json.loads((out / "meta.json").read_text())
    assert meta["rc"] == rc and meta["finished"] is not None
    kept = 3 if fails_with is KeyboardInterrupt else 2
    assert meta["episodes_written"] == kept == len((out / "results.csv").read_text().splitlines()) - 1
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_eval_never_replaces_a_meta_json_a_person_wrote(tmp_path):
    """A meta.json without eval's marker (a person's, with notes) stays as it was (``overwrite=true`` replaces
    results.csv and results.md only); one that eval wrote is replaced by the next run's."""
    mine = '{"command": "python -m eval ...", "note": "written by hand"}\n'
    (tmp_path / "meta.json").write_text(mine)
    kept = EvalMeta(tmp_path, {"episodes": 2}, ["episodes=2"])
    assert kept.kept and kept.write(2) is None and kept.end(0) is None
    assert (tmp_path / "meta.json").read_text() == mine
    (tmp_path / "meta.json").unlink()
    for episodes in (2, 1):  # the second run's replaces the first's
        meta = EvalMeta(tmp_path, {"episodes": episodes}, [f"episodes={episodes}"])
        assert not meta.kept and meta.end(0) == tmp_path / "meta.json"
        assert json.loads((tmp_path / "meta.json").read_text())["command"] == f"python -m eval episodes={episodes}"


def test_eval_refuses_an_out_dir_with_a_hand_written_meta_json_before_any_episode(tmp_path, monkeypatch, capsys):
    """Results beside a person's meta.json would leave it describing another run: ``overwrite=true`` is refused in
    one line naming the file and what to do, before any episode; the folder stays as it was (without results
    too, or with a meta.json that is not JSON). A meta.json eval wrote is replaced by ``overwrite=true``."""
    out = tmp_path / "out"
    out.mkdir()
    mine = '{"command": "python -m eval ...", "note": "written by hand"}\n'
    (out / "meta.json").write_text(mine)
    (out / "results.csv").write_text("agent,episode\n")
    with pytest.raises(SystemExit) as exit_:
        _eval(tmp_path, monkeypatch, argv=[*ARGV, "overwrite=true"])  # _eval's stand-in episodes would write rows
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert "out_dir=out holds out/meta.json" in err[0] and "move or delete it" in err[0]
    assert (out / "meta.json").read_text() == mine and (out / "results.csv").read_text() == "agent,episode\n"
    (out / "results.csv").unlink()
    assert "move or delete it" in hand_written_problem(out)  # no results: refused all the same
    (out / "meta.json").write_text("notes, not JSON\n")
    assert "move or delete it" in hand_written_problem(out)
    (out / "meta.json").unlink()
    assert hand_written_problem(out) is None
    EvalMeta(out, {"episodes": 9}, ["episodes=9"]).end(0)  # eval's own: no refusal, replaced by the next run's
    assert hand_written_problem(out) is None
    _eval(tmp_path, monkeypatch, argv=[*ARGV, "overwrite=true"])
    meta = json.loads((out / "meta.json").read_text())
    assert meta["command"] == "python -m eval " + " ".join([*ARGV, "overwrite=true"]) and meta["episodes_written"] == 4


def test_every_shipped_result_folder_is_refused_as_an_out_dir():
    """A docs/results folder's meta.json copied from an eval run keeps eval's ``written_by`` unless it is taken out,
    and then ``python -m eval out_dir=<a docs/results folder> overwrite=true`` would replace the shipped results (and add
    results.md beside them): every shipped meta.json must read as a person's. Fails when one carries the marker."""
    from pathlib import Path

    metas = sorted((Path(__file__).resolve().parents[1] / "docs" / "results").glob("*/meta.json"))
    assert metas
    replaceable = [str(m.parent.name) for m in metas if hand_written_problem(m.parent) is None]
    assert not replaceable, f"docs/results folders eval would write over (drop \"written_by\"): {replaceable}"


def test_a_run_that_fails_before_any_row_writes_no_meta_json(tmp_path):
    """Nothing measured, nothing written: the folder stays as it was (a rerun is not refused for it)."""
    meta = EvalMeta(tmp_path, {}, [])
    assert meta.end(1) is None and not (tmp_path / "meta.json").exists()


def test_a_refused_eval_leaves_the_meta_json_of_the_results_it_refuses_to_replace(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.csv").write_text("agent,episode\n")
    EvalMeta(out, {}, ["episodes=9"]).end(0)
    before = (out / "meta.json").read_text()
    with pytest.raises(SystemExit) as exit_:
        _eval(tmp_path, monkeypatch)
    assert exit_.value.code == 2 and (out / "meta.json").read_text() == before


def test_the_commit_is_none_outside_a_checkouts_top(tmp_path):
    """An installed copy inside a checkout (its .venv) would otherwise report the checkout's HEAD."""
    assert code_commit(tmp_path) is None


def test_a_git_archive_snapshot_names_its_commit(tmp_path):
    """``git archive`` fills eval/archive_commit.txt (.gitattributes export-subst): code_commit of the extracted
    snapshot (no checkout there) is HEAD's hash; in the checkout the file holds the placeholder, read as no
    commit. Fails without the export-subst line (the snapshot's file is the placeholder: None)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0:
        pytest.skip("the tests do not run from a git checkout")
    archive = subprocess.run(["git", "-C", str(root), "archive", "HEAD", "eval", ".gitattributes"],
                             capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(tmp_path, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    assert code_commit(tmp_path) == head.stdout.strip()
    assert archived_commit(root) is None  # the checkout's own file: the placeholder
    (tmp_path / "eval" / "archive_commit.txt").write_text("$Format:%H$\n")  # a wheel built from a checkout
    assert code_commit(tmp_path) is None


@pytest.mark.slow  # a real episode through python -m eval (~5 s on a loaded machine)
def test_a_real_tiny_eval_writes_meta_json_with_its_settings(tmp_path, monkeypatch):
    """The same, with the episodes played (no stand-in): meta.json's counts agree with results.csv."""
    import csv

    from eval import __main__ as eval_main

    argv = ["agents=[always_proceed]", "episodes=1", "seed=1000007", "out_dir=out", "progress_bar=false",
            "hydra.run.dir=hydra"]
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["eval", *argv])
    eval_main.main()
    meta = json.loads((tmp_path / "out" / "meta.json").read_text())
    rows = list(csv.DictReader((tmp_path / "out" / "results.csv").open()))
    assert meta["command"] == "python -m eval " + " ".join(argv) and meta["rc"] == 0
    assert meta["episodes_written"] == len(rows) == 1 and int(rows[0]["seed"]) == 1000007
    assert meta["seeds"] == [1000007, 1000007] and meta["split"] == rows[0]["split"] == "validation"
    assert meta["wall_s"] > 0 and meta["cpu_s"] > 0
