"""Nothing lost, everywhere a tool writes: the shipped references are read-only to every tool whatever
its run_name, paths or flags; every tool that writes a run or an export folder takes that folder's lock and
replaces another run's files only when asked; the side tools check what they are given in one line; and a run
stopped before its first checkpoint is told what starts it again. One test per reproduction of the issue."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from tests.test_bad_input import check_line
from tests.test_nothing_lost import REF, cli, released, shipped, snapshot  # noqa: F401 - fixtures

ROOT = Path(__file__).resolve().parents[1]
LANE = ["agent=ppo", "env=lane_keeping", "sensors=gnss_imu"]


def locked_by_another(folder: Path, pid: int = 4242) -> int:
    """An flock on ``folder/.lock`` through a separate open file description, which flock treats as another
    owner (another process); returns its descriptor, to close."""
    import fcntl

    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / ".lock", os.O_RDWR | os.O_CREAT)
    os.write(fd, f"{pid}\n".encode())
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return fd


# ------------------------------------------------------------------------------------ train and the shipped references
WHERE = [
    ["paths.checkpoints={root}/..", "run_name=reference"],  # run_name=reference: every shipped agent
    ["paths.checkpoints={root}", "run_name=ppo_turn"],  # one shipped agent
    ["paths.checkpoints={root}/../..", "run_name={parent}"],  # the folder that holds them
    ["run_name={parent}", "paths.runs={root}/../.."],  # a log folder (train.overwrite=true clears it) that holds them
]
FLAGS = [[], ["train.overwrite=true"], ["train.resume=true"]]


# fast: every folder with train.overwrite=true (the flag that deleted them) and one folder with each flag; the
# other 6 pairs (~0.2 s of Hydra each) are slow
@pytest.mark.parametrize("where, flags", [
    pytest.param(w, f, marks=() if f == ["train.overwrite=true"] or w is WHERE[1] else pytest.mark.slow,
                 id=f"where{i}-{f[0] if f else 'no_flag'}")
    for f in FLAGS for i, w in enumerate(WHERE)])
def test_train_never_writes_the_shipped_references(where, flags, shipped, tmp_path, monkeypatch, capsys, released):
    """``run_name=reference train.overwrite=true`` deleted every shipped reference (exit 0), and
    ``paths.checkpoints=checkpoints/reference run_name=ppo_turn`` replaced ppo_turn; the refusal without the flag
    suggested the flag. Refused whatever the flags, by a line that suggests none."""
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    argv = [a.format(root=shipped, parent=shipped.parent.name) for a in where]
    line = check_line("train", ["agent=dagger_turn", "env=left_turn", "sensors=turn_truth", *argv, *flags],
                      monkeypatch, capsys)
    assert "the shipped reference agents' folder" in line and "read-only to every tool" in line, line
    assert "overwrite" not in line and "resume" not in line, line
    assert snapshot(tmp_path) == before


def test_clearing_a_run_refuses_a_hydra_folder_that_holds_the_references(shipped, tmp_path, monkeypatch, released):
    """``hydra.run.dir`` is the user's too: clearing for ``train.overwrite=true`` refuses a log folder that holds
    the shipped references, even for a run of its own."""
    from av_gym.errors import ConfigError
    from train.run_folder import claim, clear_for_overwrite

    ckpt = claim(tmp_path / "checkpoints" / "R", None, resume=False, overwrite=True)
    before = snapshot(shipped)
    with pytest.raises(ConfigError, match="paths.runs/run_name=.*: holds the shipped reference agents' folder"):
        clear_for_overwrite(ckpt, shipped.parent)
    assert snapshot(shipped) == before


# ---------------------------------------------------------------------------- a run stopped before its first checkpoint
def dead_run(tmp_path: Path) -> Path:
    """A PPO run killed before its first checkpoint: the config.yaml train writes first, nothing else."""
    from tests.test_reliability import a_run

    ckpt = a_run(tmp_path, "R", LANE)
    for name in ("latest.zip", "model.zip"):
        (ckpt / name).unlink()
    return ckpt


def test_a_run_stopped_before_its_first_checkpoint_is_told_what_starts_it_again(tmp_path, monkeypatch, capsys,
                                                                                 released):
    """The refusal advised ``train.resume=true``, which then refused (no latest.zip). Both refusals now give the
    advice that works, and following it is accepted."""
    from train import __main__ as train_main
    import sys

    monkeypatch.chdir(tmp_path)
    dead_run(tmp_path)
    for flags in ([], ["train.resume=true"]):
        line = check_line("train", [*LANE, "run_name=R", *flags], monkeypatch, capsys)
        assert "stopped before its first checkpoint" in line, line
        assert "start it again with train.overwrite=true" in line, line
        assert "continue it with train.resume=true" not in line, line
    monkeypatch.setattr(sys, "argv", ["train", *LANE, "run_name=R", "train.overwrite=true"])
    train_main._check_command_line()  # the advice works: the run is claimed


def test_a_finished_run_is_not_told_to_resume(tmp_path, monkeypatch, capsys, released):
    """A finished run (its model.zip) refuses train.resume=true, so the refusal of a second run does not advise
    it; a rule-based run (config.yaml only) is a finished run, not a dead start."""
    from tests.test_reliability import a_run

    monkeypatch.chdir(tmp_path)
    a_run(tmp_path, "R", LANE)
    line = check_line("train", [*LANE, "run_name=R"], monkeypatch, capsys)
    assert "already holds a run" in line and "train.resume" not in line, line
    a_run(tmp_path, "rule", ["agent=always_proceed"])
    for name in ("latest.zip", "model.zip"):
        (tmp_path / "checkpoints" / "rule" / name).unlink()
    line = check_line("train", ["agent=always_proceed", "run_name=rule"], monkeypatch, capsys)
    assert "already holds a run (config.yaml)" in line and "stopped before" not in line, line


# --------------------------------------------------------------------- export and operating point: the destination's
@pytest.fixture
def two_runs(tmp_path):
    """checkpoints/A and checkpoints/B: two training runs' folders (copies of dagger_turn, a GO/YIELD student both
    tools take), B with a latest.zip of its own."""
    runs = {}
    for name in ("A", "B"):
        runs[name] = tmp_path / "checkpoints" / name
        shutil.copytree(REF / "dagger_turn", runs[name])
    shutil.copy(runs["B"] / "model.zip", runs["B"] / "latest.zip")
    (runs["B"] / "config.yaml").write_text((runs["B"] / "config.yaml").read_text() + "# B's own\n")
    return runs


def export_argv(tool: str, a: Path, b: Path | str) -> list[str]:
    return [str(a), str(b)] if tool == "export" else [str(a), "--write", "0.5", "--dest", str(b)]


def tool_main(tool: str):
    from train.export import main as export_main
    from train.operating_point import main as operating_point_main

    return export_main if tool == "export" else operating_point_main


@pytest.mark.parametrize("tool", ["export", "operating_point"])
def test_a_tool_does_not_replace_another_runs_model(tool, two_runs, capsys):
    """``train.export A B`` and ``train.operating_point A --write 0.5 --dest B`` replaced run B's model, leaving it
    beside A's config. Refused in one line; ``--overwrite`` replaces B's files, all of them (no mix of two runs)."""
    a, b = two_runs["A"], two_runs["B"]
    before = snapshot(b)
    line = cli(tool_main(tool), export_argv(tool, a, b), capsys)
    assert f"dest={b} already holds COMMAND, config.yaml, latest.zip ..." in line and "--overwrite" in line, line
    assert snapshot(b) == before
    tool_main(tool)([*export_argv(tool, a, b), "--overwrite"])
    after = snapshot(b)
    assert sorted(after) == sorted(["config.yaml", "model.zip", *(["COMMAND"] if tool == "operating_point" else [])])
    assert b"# B's own" not in after["config.yaml"] and not (b / ".lock").exists()


@pytest.mark.parametrize("tool", ["export", "operating_point"])
def test_a_tool_does_not_write_a_run_in_training(tool, two_runs, capsys):
    """Run B in training holds its folder's lock (python -m train): refused even with --overwrite, B untouched."""
    a, b = two_runs["A"], two_runs["B"]
    (b / "model.zip").unlink()  # still training: no final model yet
    fd = locked_by_another(b)
    before = snapshot(b)
    try:
        line = cli(tool_main(tool), [*export_argv(tool, a, b), "--overwrite"], capsys)
    finally:
        os.close(fd)
    assert f"dest={b}: another process (pid 4242) is writing it" in line, line
    assert snapshot(b) == before


@pytest.mark.parametrize("tool", ["export", "operating_point"])
def test_a_second_export_to_the_same_folder_is_refused(tool, two_runs, tmp_path, capsys):
    """A second export into the same folder silently replaced the first."""
    a, out = two_runs["A"], tmp_path / "checkpoints" / "out"
    tool_main(tool)(export_argv(tool, a, out))
    first = snapshot(out)
    assert "model.zip" in first and not (out / ".lock").exists()
    line = cli(tool_main(tool), export_argv(tool, two_runs["B"], out), capsys)
    assert "already holds" in line, line
    assert snapshot(out) == first


@pytest.mark.parametrize("dest", ["", "."])
def test_an_export_to_no_folder_is_one_line(dest, two_runs, tmp_path, monkeypatch, capsys):
    """``train.export A ""`` was a traceback (``Path('.').with_name``)."""
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    line = cli(tool_main("export"), [str(two_runs["A"]), dest, "--overwrite"], capsys)
    assert "dest='.': give the folder to write" in line, line  # '' is the working directory, '.'
    assert snapshot(tmp_path) == before


def test_the_operating_point_shows_progress(capsys):
    """``train.operating_point`` printed nothing until a threshold's episodes were all measured (minutes): each
    threshold's episodes now have a progress bar on stderr."""
    from train.operating_point import main

    main([str(REF / "dagger_turn"), "--thresholds", "[0.5,0.9]", "--episodes", "2"])
    out, err = capsys.readouterr()
    assert "| 0.50 |" in out and "| 0.90 |" in out
    assert "P(GO) >= 0.5" in err and "P(GO) >= 0.9" in err and "/2 [" in err, err


# ------------------------------------------------------------------------------------ eval.interventions: eval's guards
@pytest.mark.parametrize("argv, needle", [
    (["--window", "-1"], "argument --window: expected a number in [0.1, 600.0], got '-1'"),
    (["--window", "nan"], "argument --window: expected a number in [0.1, 600.0], got 'nan'"),
    (["--workers", "0"], "argument --workers: expected an integer in [1, 64], got '0'"),
    (["--episodes", "0"], "argument --episodes: expected an integer in [1, 100000], got '0'"),
    (["--seed", "-3"], "--seed=-3 with 100 episodes leaves split 'validation' (seeds 1000000..1999999)"),
    (["--seed", "1999990"], "--seed=1999990 with 100 episodes leaves split 'validation'"),  # into the test split
    (["--seed", "1000"], "--seed=1000 with 100 episodes leaves split 'validation'"),  # a train seed
    (["--split", "test", "--seed", "1000000"], "leaves split 'test'"),
    (["--out", "/proc/x"], "--out=/proc/x: nothing can be created in '/proc'"),
    (["--agents", "[always_proceed]"], "--agents: 'always_proceed' has no shield: use an agent+aeb spec"),
])
def test_interventions_checks_its_flags_in_one_line(argv, needle, tmp_path, monkeypatch, capsys):
    """``--window -1``/``nan`` and ``--workers 0`` were accepted, ``--seed -3`` and ``--out /proc/x`` were
    tracebacks, ``--episodes 0`` printed a 689 KB line (argparse listing choices=range(1, 100001)), seeds outside
    their split were accepted. Each is one short line, exit 2, before any episode; nothing is written."""
    from eval.interventions import main

    monkeypatch.chdir(tmp_path)
    line = cli(lambda args: main(args), argv, capsys)
    assert needle in line and len(line) < 300, line
    assert list(tmp_path.iterdir()) == []


def test_interventions_does_not_replace_another_runs_tables(tmp_path, capsys):
    """Two runs into one --out: the second's tables replaced the first's (or both wrote at once and one's rows were
    lost). The folder is held while a run writes it and its tables are replaced only with --overwrite."""
    from eval.interventions import main

    out = tmp_path / "iv"
    argv = ["--agents", "[always_proceed+aeb]", "--episodes", "1", "--out", str(out)]
    assert main(argv) == 0
    first = snapshot(out)
    assert sorted(first) == ["episodes.csv", "interventions.csv", "interventions.md"]
    line = cli(lambda args: main(args), [*argv, "--seed", "1000001"], capsys)
    assert f"--out={out} already holds episodes.csv, interventions.csv, interventions.md" in line, line
    assert "--overwrite" in line and snapshot(out) == first
    fd = locked_by_another(out)
    try:
        line = cli(lambda args: main(args), [*argv, "--overwrite"], capsys)
    finally:
        os.close(fd)
    assert f"--out={out}: another eval.interventions (pid 4242) is writing it" in line, line
    assert snapshot(out) == {**first, ".lock": b"4242\n"}
    (out / ".lock").unlink()
    assert main([*argv, "--seed", "1000001", "--overwrite"]) == 0
    assert "1000001" in (out / "episodes.csv").read_text() and not (out / ".lock").exists()


# ------------------------------------------------------------------------------------ python -m eval: what it records
@pytest.mark.parametrize("argv, needle", [
    (["vec_env=batched", "sensors=cameras", "agents=[always_proceed]"],
     "agent 'always_proceed': sensors.cameras is not available with vec_env=batched"),
    (["sensors=turn_perceived", "agents=[ppo_turn]"],
     "sensors=turn_perceived: agent 'ppo_turn' runs on the sensors it was trained with (turn_truth), so "
     "sensors=turn_perceived would not reach it; drive it from turn_perceived with agents=[ppo_turn@turn_perceived]"),
    (["sensors=cameras", "agents=[ppo_turn+aeb]"], "agents=[ppo_turn@cameras+aeb]"),
])
def test_eval_refuses_sensors_that_would_not_run(argv, needle, tmp_path, monkeypatch, capsys):
    """``vec_env=batched sensors=cameras`` ran truth features and recorded ``cameras`` in results.md;
    ``sensors=<preset>`` with a trained agent was ignored without a word. One line each, before any folder."""
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", [*argv, "episodes=2"], monkeypatch, capsys)
    assert needle in line, line
    assert list(tmp_path.iterdir()) == []


def test_the_batch_records_the_sensors_it_ran(monkeypatch):
    """always_proceed on the batch runs the batch's own features, whatever the default preset says: its plan (what
    results.md records) says so; on the per-env stack it runs, and records, the preset given."""
    from conf.check import check_command_line
    from conf.commands import EvalCommand
    from eval.__main__ import _plans

    for vec_env, name in (("batched", "turn_truth"), ("subproc", "truth")):
        (cfg,) = check_command_line("eval", [f"vec_env={vec_env}", "agents=[always_proceed,gap_acceptance]"])
        plans = _plans(cfg, EvalCommand.of(cfg))
        assert [p.sensors["name"] for p in plans] == [name, "turn_truth"], vec_env


def test_a_trained_agent_on_its_own_preset_is_still_accepted(tmp_path, monkeypatch, released):
    """The documented ``agents=[checkpoints/reference/pilotnet] sensors=cameras`` (its own preset, with overrides)
    and the default preset are not refused."""
    import sys

    from eval import __main__ as eval_main

    monkeypatch.chdir(tmp_path)
    for argv in (["env=lane_keeping", f"agents=[{REF / 'pilotnet'}]", "sensors=cameras", "sensors.cameras.night=true"],
                 ["agents=[ppo_turn]"]):
        monkeypatch.setattr(sys, "argv", ["eval", *argv])
        eval_main._check_command_line()


@pytest.mark.parametrize("overwrite", [[], ["overwrite=true"]])
def test_eval_never_writes_into_a_shipped_reference(overwrite, shipped, tmp_path, monkeypatch, capsys, released):
    """``out_dir=checkpoints/reference/ppo_turn`` wrote results.csv and results.md into a shipped reference."""
    monkeypatch.chdir(tmp_path)
    before = snapshot(shipped)
    line = check_line("eval", ["agents=[always_proceed]", f"out_dir={shipped}/ppo_turn", *overwrite],
                      monkeypatch, capsys)
    assert "is inside the shipped reference agents' folder" in line and "overwrite" not in line, line
    assert snapshot(shipped) == before


# ------------------------------------------------------------------------------------- Hydra's files under a size limit
@pytest.mark.slow  # the same hydra_files_whole around both commands' Hydra, each a process under a limit (~6 s idle)
@pytest.mark.parametrize("argv", [
    ["eval", "agents=[always_proceed]", "episodes=1", "progress_bar=false"],
    ["train", "agent=always_proceed", "train.eval_episodes=0", "run_name=R"],
])
def test_hydra_files_that_cannot_be_written_are_one_line_and_nothing_is_left(argv, tmp_path):
    """Under ``ulimit -f 1`` Hydra's config save was a traceback and left a torn ``.hydra`` folder. One line,
    exit 2, and the working folder as it was (no run folder, no checkpoints folder, no lock)."""
    import resource
    import subprocess
    import sys

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (1024, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONDONTWRITEBYTECODE": "1"}
    proc = subprocess.run([sys.executable, "-m", *argv], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300, preexec_fn=limit)
    err = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(err) == 1, (proc.returncode, proc.stderr[-3000:])
    assert err[0].startswith("error: hydra.run.dir: cannot write ") and "File too large" in err[0], err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("tool", ["export", "operating_point"])
def test_overwrite_never_replaces_a_folder_of_runs(tool, two_runs, shipped, tmp_path, capsys):
    """``--overwrite`` replaces one checkpoint's files: a folder of runs (``checkpoints/``) or one that holds the
    shipped references is refused whatever the flags, nothing in it touched."""
    before = snapshot(tmp_path)
    line = cli(tool_main(tool), [*export_argv(tool, two_runs["A"], tmp_path / "checkpoints"), "--overwrite"], capsys)
    assert "holds folders (A, B, lane), so it is not one checkpoint's folder" in line, line
    line = cli(tool_main(tool), [*export_argv(tool, two_runs["A"], tmp_path), "--overwrite"], capsys)
    assert f"dest={tmp_path}: holds the shipped reference agents' folder" in line, line
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("tool", ["eval.interventions", "eval.results_page", "eval.ccftap"])
def test_side_tools_never_write_into_a_shipped_reference(tool, shipped, capsys):
    """The side tools' ``--out`` (conf/cli.py ``out_folder_problem``, ``out_file_problem``) inside the shipped
    references: one line, nothing written there."""
    import importlib
    import sys

    main = importlib.import_module(tool).main
    out = shipped / "ppo_turn" / ("page.md" if tool == "eval.results_page" else "out")
    before = snapshot(shipped)
    line = cli(lambda argv: sys.exit(main(argv)), ["--out", str(out)], capsys)  # as its command line runs it
    assert "is inside the shipped reference agents' folder" in line, line
    assert snapshot(shipped) == before


@pytest.mark.parametrize("module, argv", [
    ("eval", ["agents=[always_proceed]", "hydra.run.dir={root}/ppo_turn"]),
    ("train", ["agent=always_proceed", "run_name=R", "hydra.run.dir={root}/ppo_turn"]),
    ("train", ["agent=always_proceed", "run_name=R", "hydra.run.dir={root}/.."]),  # cleared by train.overwrite=true
])
def test_a_hydra_folder_in_the_shipped_references_is_refused(module, argv, shipped, tmp_path, monkeypatch, capsys,
                                                              released):
    """``hydra.run.dir`` is where Hydra writes ``.hydra/`` (and eval its results, train its logs) before the job
    runs: inside the shipped references (or, for train, holding them) it is refused before Hydra writes."""
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    line = check_line(module, [a.format(root=shipped) for a in argv], monkeypatch, capsys)
    assert "hydra.run.dir=" in line and "the shipped reference agents' folder" in line, line
    assert snapshot(tmp_path) == before
