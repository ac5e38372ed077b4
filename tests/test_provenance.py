"""What ran is recorded with the rows (R7 finding 4): the env preset and its changed fields in meta.json, results.md
and the results page; the code's commit with a dirty mark (and the changed tracked files) in meta.json and in a
training run's provenance.json; the trained agent's brief-evaluation label says the shield it ran behind."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from av_gym.presets import compose_group
from eval.meta import EvalMeta, env_as_ran, provenance
from eval.report import write_results
from eval.results_page import _where

LANE_B = {**compose_group("env", "lane_keeping"), "track": "B"}


def _git(root: Path, *args: str) -> None:
    subprocess.run(["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t", *args], check=True,
                   capture_output=True)


def test_a_dirty_checkout_is_marked_with_its_changed_files(tmp_path):
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "b.py").write_text("y = 1\n")
    _git(tmp_path, "add", "a.py", "b.py")
    _git(tmp_path, "commit", "-q", "-m", "c")
    clean = provenance(tmp_path)
    assert clean["dirty"] is False and "changed" not in clean and len(clean["commit"]) == 40
    (tmp_path / "a.py").write_text("x = 2\n")  # edited, not committed: the numbers are not the commit's
    (tmp_path / "notes.txt").write_text("mine")  # untracked: not code that ran
    dirty = provenance(tmp_path)
    assert (dirty["commit"], dirty["dirty"], dirty["changed"]) == (clean["commit"], True, ["a.py"])
    assert set(dirty["versions"]) >= {"numpy", "torch", "gymnasium", "highway-env", "stable-baselines3"}


def test_no_git_says_so(tmp_path):
    """An archive or a wheel: no commit to name unless the archive carries one, and no way to tell dirty."""
    record = provenance(tmp_path)
    assert (record["commit"], record["dirty"]) == (None, None) and "changed" not in record


def test_meta_json_and_results_md_name_the_env_and_its_changed_fields(tmp_path):
    assert env_as_ran(LANE_B) == {"preset": "lane_keeping", "changed": {"track": "B"}}
    assert env_as_ran(compose_group("env", "left_turn")) == {"preset": "left_turn", "changed": {}}
    meta = EvalMeta(tmp_path, {"split": "validation"}, ["env.track=B"], LANE_B)
    meta.write(1)
    data = json.loads((tmp_path / "meta.json").read_text())
    assert data["env"] == {"preset": "lane_keeping", "changed": {"track": "B"}} and "dirty" in data
    row = {"agent": "pid_paper", "seed": 1000000, "lap_completed": 1.0, "cte_mean_abs_m": 0.2}
    write_results([row], tmp_path, "lane_keeping", "t", env=env_as_ran(LANE_B))
    assert "## Env the episodes ran in\n\n- `lane_keeping` with track='B'\n" in (tmp_path / "results.md").read_text()
    write_results([row], tmp_path, "lane_keeping", "t", env=env_as_ran(compose_group("env", "lane_keeping")))
    assert "- `lane_keeping` (as shipped)" in (tmp_path / "results.md").read_text()


def test_the_results_page_reads_the_env_from_meta_json_not_the_command():
    """meta.json's ``env`` decides (a sweep cell's command, or one given from Python, may not hold env.track=);
    a folder written before it (the shipped ones) still reads its command's env.track=."""
    new = {"command": "python -m eval env=lane_keeping", "env": {"preset": "lane_keeping", "changed": {"track": "B"}}}
    assert _where({"scenario": "lane_keeping", "meta": new}) == "lane keeping, layout B"
    turn = {"command": "python -m eval", "env": {"preset": "left_turn", "changed": {"mode": "ccftap"}}}
    assert _where({"scenario": "left_turn", "meta": turn}) == "left turn (mode='ccftap')"
    old = {"command": "python -m eval env=lane_keeping env.track=C 'agents=[pid_paper]'"}
    assert _where({"scenario": "lane_keeping", "meta": old}) == "lane keeping, layout C"
    assert _where({"scenario": "lane_keeping", "meta": {"command": "python -m eval"}}) == "lane keeping"


def test_the_results_page_says_a_folder_came_from_uncommitted_code(tmp_path):
    from eval.results_page import load_folder, page

    row = {"agent": "pid_paper", "seed": 1000000, "lap_completed": 1.0, "cte_mean_abs_m": 0.2}
    write_results([row], tmp_path, "lane_keeping", "t")
    meta = {"command": "python -m eval", "commit": "a" * 40, "started": "s", "finished": "f", "wall_s": 1,
            "load": "1-1", "rc": 0}
    (tmp_path / "meta.json").write_text(json.dumps({**meta, "dirty": True, "changed": ["agents/rules.py"]}))
    said = page([load_folder(tmp_path)])
    assert "- commit `aaaaaaaaaa` with uncommitted changes to `agents/rules.py`, s to f" in said
    (tmp_path / "meta.json").write_text(json.dumps({**meta, "dirty": False}))
    assert "- commit `aaaaaaaaaa`, s to f" in page([load_folder(tmp_path)])


def test_a_training_run_records_its_code_and_each_resume(tmp_path):
    from train.provenance import PROVENANCE, record_start
    from train.run_folder import LOG_NAMES, not_a_runs

    assert PROVENANCE in LOG_NAMES  # overwrite removes it; it is never taken for a user's file
    record_start(tmp_path, ["agent=ppo_turn"], resume=False)
    record_start(tmp_path, ["agent=ppo_turn", "train.resume=true"], resume=True)
    runs = json.loads((tmp_path / PROVENANCE).read_text())["runs"]
    assert [r["resume"] for r in runs] == [False, True]
    assert runs[0]["command"] == "python -m train agent=ppo_turn" and {"commit", "dirty", "versions"} <= set(runs[1])
    record_start(tmp_path, None, resume=False)  # a fresh start (overwrite) begins the list again
    assert len(json.loads((tmp_path / PROVENANCE).read_text())["runs"]) == 1
    assert not_a_runs(tmp_path, logs=True) == []
    assert not list(tmp_path.glob("*.tmp"))  # written atomically: no temporary left


def test_a_start_the_trainer_refuses_leaves_no_provenance(tmp_path):
    """A fresh run refused by its trainer: no provenance.json is left to make runs/<run>/ look taken (Hydra's own
    files there are discarded); a refused resume drops only its own entry."""
    from train.provenance import PROVENANCE, record_start, undo_start

    record_start(tmp_path, ["run_name=R"], resume=False)
    undo_start(tmp_path, resume=False)
    assert not (tmp_path / PROVENANCE).exists()
    record_start(tmp_path, ["run_name=R"], resume=False)
    record_start(tmp_path, ["run_name=R", "train.resume=true"], resume=True)
    undo_start(tmp_path, resume=True)
    assert [r["resume"] for r in json.loads((tmp_path / PROVENANCE).read_text())["runs"]] == [False]


def test_the_trained_agents_row_says_the_command_lines_shield(monkeypatch):
    """``python -m train agent=ppo_turn shield=aeb``: its own brief-evaluation row is ``ppo_turn+aeb``, not the
    bare name (eval/labels.py row_label, as every other row)."""
    from conf.check import check_command_line
    from conf.commands import TrainCommand
    from train import __main__ as train_main

    (cfg,) = check_command_line("train", ["agent=ppo_turn", "shield=aeb", "train.eval_episodes=1"])

    class Built(Exception):
        pass

    def make_env(env_cfg, sensors, shield, **kwargs):
        raise Built

    monkeypatch.setattr("av_gym.make.make_env", make_env)
    folders = train_main.Folders(run_dir=None, ckpt_dir=Path("checkpoints/reference/ppo_turn"))
    ran_with: dict = {}
    shields: dict = {}
    with pytest.raises(Built):
        train_main._evaluate_spec(cfg, TrainCommand.of(cfg), folders, str(folders.ckpt_dir), range(1), [], ran_with,
                                  shields)
    assert list(ran_with) == list(shields) == [f"{cfg.agent.name}+aeb"]


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    import os
    import sys

    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.slow  # ~10-20 s: python -m eval and python -m train, one episode each
def test_eval_and_train_write_the_env_and_the_code_with_their_rows(tmp_path):
    """R7's command: ``env.track=B`` is in meta.json and results.md (and so on the page); a training run's log
    folder holds provenance.json and its results.md names the changed env field."""
    res = _run(["eval", "env=lane_keeping", "env.track=B", "agents=[pid_paper]", "episodes=1", "out_dir=out",
                "progress_bar=false", "videos=false", "hydra.run.dir=hydra"], tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    meta = json.loads((tmp_path / "out" / "meta.json").read_text())
    assert meta["env"] == {"preset": "lane_keeping", "changed": {"track": "B"}} and "dirty" in meta
    assert "- `lane_keeping` with track='B'" in (tmp_path / "out" / "results.md").read_text()
    res = _run(["train", "agent=always_proceed", "env.duration=13", "train.eval_episodes=1", "run_name=R",
                "train.progress_bar=false"], tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    runs = json.loads((tmp_path / "runs" / "R" / "provenance.json").read_text())["runs"]
    assert len(runs) == 1 and runs[0]["command"].startswith("python -m train agent=always_proceed")
    assert "- `left_turn` with duration=13" in (tmp_path / "runs" / "R" / "results.md").read_text()


@pytest.mark.slow  # ~2 s at load 4: train's composition and folder claim
def test_train_undoes_the_record_of_a_start_its_trainer_refused(tmp_path, monkeypatch):
    """train.__main__ itself: the trainer refuses (as an agent.init_from that does not fit): nothing of the run's
    is left in its log folder, provenance.json included (test_nothing_lost checks its checkpoint folder)."""
    from types import SimpleNamespace

    import train.registry
    from av_gym.errors import ConfigError
    from conf.check import check_command_line
    from tests.test_reliability import LANE
    from train import __main__ as train_main
    from train.run_folder import release_all

    monkeypatch.chdir(tmp_path)
    (cfg,) = check_command_line("train", [*LANE, "run_name=R", "train.eval_episodes=0"])
    logs = tmp_path / "runs" / "R"
    hydra = SimpleNamespace(runtime=SimpleNamespace(output_dir=str(logs)), mode=None)
    monkeypatch.setattr(train_main.HydraConfig, "get", staticmethod(lambda: hydra))

    def refuses(cfg, ckpt_dir, run_dir, **_):
        assert (run_dir / "provenance.json").is_file()  # recorded before the trainer ran
        raise ConfigError("agent.init_from='x': checkpoint 'x' was trained on env 'lane_keeping', not 'left_turn'")

    real = train.registry.trainer_of
    monkeypatch.setattr(train.registry, "trainer_of", lambda kind: refuses if kind == "ppo" else real(kind))
    try:
        with pytest.raises(ConfigError, match="was trained on env"):
            train_main.train(cfg)
    finally:
        release_all()
    assert not (logs / "provenance.json").exists()
