"""Nothing shipped or measured can be lost: the shipped references are read-only to the tools, an evaluation owns
its out_dir, every generated file is written whole or not at all, resuming never replaces work (DAgger resumes at a
round), every count has an upper bound, and what is refused or interrupted says so in one line and leaves nothing
behind."""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
REF = ROOT / "checkpoints" / "reference"


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def no_space(*_args, **_kw):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def one_line(capsys, code: int, exit_: pytest.ExceptionInfo) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == code and len(err) == 1 and err[0].startswith("error: "), (exit_.value.code, err)
    return err[0]


def cli(main, argv: list[str], capsys) -> str:
    """``main(argv)`` as its command line runs it (:func:`av_gym.errors.run_cli`): its one error line, exit 2."""
    from av_gym.errors import run_cli

    with pytest.raises(SystemExit) as exit_:
        run_cli(main, argv)
    return one_line(capsys, 2, exit_)


# ----------------------------------------------------------------------------------------------- the shipped references
@pytest.fixture
def shipped(tmp_path, monkeypatch):
    """A stand-in for checkpoints/reference/ (copies of ppo_turn and dagger_turn), which the tools take for the
    shipped folder; and a lane-keeping run beside it."""
    import av_gym.references

    root = tmp_path / "reference"
    for name in ("ppo_turn", "dagger_turn"):
        shutil.copytree(REF / name, root / name)
    monkeypatch.setattr(av_gym.references, "reference_root", lambda: root)
    lane = tmp_path / "checkpoints" / "lane"
    shutil.copytree(REF / "ppo_lane_localized", lane)
    return root


@pytest.mark.parametrize("argv, needle", [
    # a lane keeper exported over ppo_turn
    (["{lane}", "{ref}/ppo_turn", "--command", "x"], "is the shipped reference agent 'ppo_turn'"),
    (["{lane}", "{ref}/ppo_turn", "--command", "x", "--overwrite-reference"],
     "holds 'ppo_turn' with env.name=left_turn, this checkpoint has env.name=lane_keeping"),
    (["{ref}/dagger_turn", "{ref}/ppo_turn", "--command", "x", "--overwrite-reference"],
     "holds 'ppo_turn' with agent.kind=ppo, this checkpoint has agent.kind=dagger"),
    (["{ref}/ppo_turn", "{ref}/ppo_turn", "--overwrite-reference"], "give the command that made the new checkpoint"),
    (["{lane}", "{ref}", "--command", "x", "--overwrite-reference"], "is the folder of every shipped reference"),
])
def test_export_does_not_write_over_a_shipped_reference(argv, needle, shipped, tmp_path, capsys):
    from train.export import main

    lane = tmp_path / "checkpoints" / "lane"
    before = snapshot(shipped)
    line = cli(main, [a.format(lane=lane, ref=shipped) for a in argv], capsys)
    assert needle in line, line
    assert snapshot(shipped) == before


@pytest.mark.parametrize("argv, needle", [
    # the operating point of dagger_turn written over ppo_turn
    (["{ref}/dagger_turn", "--write", "0.8", "--dest", "{ref}/ppo_turn"], "is the shipped reference agent 'ppo_turn'"),
    (["{ref}/dagger_turn", "--write", "0.8", "--dest", "{ref}/ppo_turn", "--overwrite-reference"],
     "this checkpoint has agent.kind=dagger"),
    (["{ref}/dagger_turn", "--write", "0.8", "--dest", "{ref}/dagger_turn"], "is the shipped reference agent"),
    # a lane keeper has no GO logit (an IndexError in shift_go)
    (["{lane}"], "its agent chooses agent.actions=env on env=lane_keeping; the operating point is a threshold on "
                 "P(GO) of a GO/YIELD student"),
    (["{lane}", "--write", "0.8", "--dest", "{tmp}/out"], "agent.actions=env on env=lane_keeping"),
])
def test_the_operating_point_writes_no_shipped_reference_and_needs_a_go_yield_student(argv, needle, shipped, tmp_path,
                                                                                     capsys):
    from train.operating_point import main

    before = snapshot(shipped)
    line = cli(main, [a.format(lane=tmp_path / "checkpoints" / "lane", ref=shipped, tmp=tmp_path) for a in argv],
               capsys)
    assert needle in line, line
    assert snapshot(shipped) == before and not (tmp_path / "out").exists()


def test_shift_go_refuses_a_policy_without_a_go_logit():
    from agents.checkpoint import load_sb3
    from av_gym.errors import ConfigError
    from train.operating_point import shift_go

    with pytest.raises(ConfigError, match="GO/YIELD student's .* this policy has"):
        shift_go(load_sb3(REF / "ppo_lane_localized" / "model.zip", device="cpu"), 0.8)


def test_a_reference_is_replaced_whole_when_asked(shipped, tmp_path, capsys):
    """With --overwrite-reference, a checkpoint like the reference replaces model, config and COMMAND together
    (the operating point's COMMAND: the source's own, then its command); nothing hidden is left beside it."""
    from train.operating_point import main

    main([str(shipped / "dagger_turn"), "--write", "0.8", "--dest", str(shipped / "dagger_turn"),
          "--overwrite-reference"])
    command = (shipped / "dagger_turn" / "COMMAND").read_text()
    assert command.startswith((REF / "dagger_turn" / "COMMAND").read_text().rstrip("\n"))
    assert "--write 0.8 --dest" in command and "--overwrite-reference" in command.splitlines()[-1]
    assert "go_threshold: 0.8" in (shipped / "dagger_turn" / "config.yaml").read_text()
    assert sorted(p.name for p in shipped.iterdir()) == ["dagger_turn", "ppo_turn"]


def test_export_into_a_reference_with_the_flag_rewrites_its_command(shipped, tmp_path):
    from train.export import export_reference

    run = tmp_path / "checkpoints" / "turn"
    shutil.copytree(REF / "ppo_turn", run)
    (run / "COMMAND").unlink()
    export_reference(run, shipped / "ppo_turn", command="python -m train seed=7", overwrite_reference=True)
    assert (shipped / "ppo_turn" / "COMMAND").read_text() == "python -m train seed=7\n"
    assert sorted(p.name for p in (shipped / "ppo_turn").iterdir()) == ["COMMAND", "config.yaml", "model.zip"]
    assert sorted(p.name for p in shipped.iterdir()) == ["dagger_turn", "ppo_turn"]


@pytest.mark.parametrize("exchange", [True, False])
def test_a_folder_replaced_on_a_full_disk_stays_whole(exchange, shipped, tmp_path, monkeypatch):
    """The folder swap: a write that fails half-way (the model saved, the disk full at COMMAND) leaves the old
    folder byte for byte and no hidden folder; with or without the kernel's exchange."""
    import av_gym.atomic
    from av_gym.atomic import WriteFailed
    from train.export import write_checkpoint_folder

    if not exchange:
        monkeypatch.setattr(av_gym.atomic, "_exchange", lambda a, b: False)
    dest = shipped / "ppo_turn"
    before = snapshot(dest)

    def half(path: Path) -> None:
        path.write_text("half")
        no_space()

    with pytest.raises(WriteFailed, match=r"dest: cannot write .*ppo_turn: No space left on device \(the previous "
                                          r"version is intact\)"):
        write_checkpoint_folder(dest, {"model.zip": "new", "config.yaml": "new", "COMMAND": half})
    assert snapshot(dest) == before and sorted(p.name for p in shipped.iterdir()) == ["dagger_turn", "ppo_turn"]
    write_checkpoint_folder(dest, {"COMMAND": "new\n"})  # the others carried over
    assert snapshot(dest) == {**before, "COMMAND": b"new\n"}
    assert sorted(p.name for p in shipped.iterdir()) == ["dagger_turn", "ppo_turn"]


# ------------------------------------------------------------------------------------------- an evaluation owns out_dir
def run(argv: list[str], cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def released():
    """What a test's command-line check locked is released afterwards (the check holds it for the life of the
    process, which here is pytest's)."""
    from eval.__main__ import OUT_DIRS
    from train.run_folder import release_all

    yield
    OUT_DIRS.release_all()
    release_all()


def test_a_second_evaluation_into_the_same_out_dir_is_refused(tmp_path, monkeypatch, capsys, released):
    """two ``python -m eval ... out_dir=X`` at once both exited 0; X held the second's rows only. Another
    process's lock (an flock on a separate open file description, which flock treats as another owner) refuses the
    second in one line, before Hydra writes anything."""
    import fcntl

    from tests.test_bad_input import check_line

    monkeypatch.chdir(tmp_path)
    (tmp_path / "X").mkdir()
    fd = os.open(tmp_path / "X" / ".lock", os.O_RDWR | os.O_CREAT)
    os.write(fd, b"4242\n")
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    try:
        line = check_line("eval", ["out_dir=X", "agents=[always_proceed]", "episodes=5"], monkeypatch, capsys)
        assert "out_dir=X: another evaluation (pid 4242) is writing it (X/.lock is locked)" in line, line
    finally:
        os.close(fd)
    assert sorted(p.name for p in tmp_path.rglob("*")) == [".lock", "X"]  # the holder's lock, nothing else


@pytest.mark.slow  # a real evaluation left running while a second one starts (~15 s)
def test_two_evaluations_into_one_out_dir_the_second_is_refused_and_the_first_keeps_its_rows(tmp_path):
    import signal
    import time

    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    first = subprocess.Popen([sys.executable, "-m", "eval", "agents=[always_proceed]", "episodes=100000",
                              "out_dir=X", "progress_bar=false"], cwd=tmp_path, env=env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        while not (tmp_path / "X" / ".lock").is_file() and time.time() < deadline:
            assert first.poll() is None, first.stderr.read()[-2000:]
            time.sleep(0.2)
        second = run(["-m", "eval", "agents=[always_proceed]", "episodes=5", "out_dir=X", "progress_bar=false"],
                     tmp_path)
        err = [line for line in second.stderr.splitlines() if line.strip()]
        assert second.returncode == 2 and len(err) == 1 and f"another evaluation (pid {first.pid}) is writing it" \
            in err[0], second.stderr[-2000:]
        time.sleep(2)
    finally:
        first.send_signal(signal.SIGTERM)  # keeps the episodes it measured
        first.wait(60)
    rows = (tmp_path / "X" / "results.csv").read_text().splitlines()
    assert len(rows) > 1 and "(interrupted after" in (tmp_path / "X" / "results.md").read_text()
    assert not (tmp_path / "X" / ".lock").exists() and not (tmp_path / "runs").exists()


def test_an_evaluation_holds_its_out_dir_then_leaves_no_lock(tmp_path, monkeypatch, released):
    from eval import __main__ as eval_main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["eval", "out_dir=X", "agents=[always_proceed]"])
    eval_main._check_command_line()
    assert (tmp_path / "X" / ".lock").read_text().strip() == str(os.getpid())
    eval_main.OUT_DIRS.release_all()
    assert not (tmp_path / "X").exists()  # made for the lock, empty: removed with it


def test_eval_with_an_out_dir_leaves_no_hydra_folder(tmp_path, monkeypatch, released):
    """``python -m eval out_dir=X`` left an empty Hydra folder runs/eval/<env>-<time>/ beside X. In this process
    (Hydra's run folder is made and removed the same way; a fresh interpreter would add ~5 CPU-s of imports)."""
    from eval import __main__ as eval_main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["eval", "agents=[always_proceed]", "episodes=1", "out_dir=X",
                                      "progress_bar=false"])
    eval_main.main()
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == ["X", "X/meta.json",
                                                                                 "X/results.csv", "X/results.md"]


# ------------------------------------------------------------------------------------- resume and refusals lose nothing
def a_run(tmp_path: Path, name: str = "R", finished: bool = True) -> Path:
    from tests.test_reliability import LANE, a_run as run_of

    ckpt = run_of(tmp_path, name, LANE)
    if not finished:
        (ckpt / "model.zip").unlink()
    return ckpt


@pytest.mark.parametrize("agent", [[], ["agent=dagger_turn", "env=left_turn", "sensors=turn_truth"]])
def test_resuming_a_finished_run_is_refused_with_nothing_touched(agent, tmp_path, monkeypatch, capsys, released):
    """``train.resume=true`` on a finished run retrained from latest.zip and replaced model.zip. A finished
    run (its model.zip, written by every trainer only at its end) is refused in one line; its files stay."""
    from tests.test_bad_input import check_line
    from tests.test_reliability import LANE, a_run as run_of

    monkeypatch.chdir(tmp_path)
    argv = [*LANE, *agent] if not agent else agent
    run_of(tmp_path, "R", argv)
    before = snapshot(tmp_path)
    line = check_line("train", [*argv, "run_name=R", "train.resume=true"], monkeypatch, capsys)
    assert "train.resume=true: run_name=R finished (checkpoints/R/model.zip is its final model), nothing to " \
           "resume; to train on from it, start a new run_name with agent.init_from=checkpoints/R" in line, line
    assert snapshot(tmp_path) == before


def test_a_config_refused_by_the_trainer_leaves_no_run_folder(tmp_path, monkeypatch):
    """an agent.init_from that does not fit, found once the job runs, was one line but left
    checkpoints/<run>/config.yaml, and the run_name was then refused as taken. Here the trainer refuses."""
    from types import SimpleNamespace

    import train.registry
    from av_gym.errors import ConfigError
    from conf.check import check_command_line
    from tests.test_reliability import LANE
    from train import __main__ as train_main
    from train.run_folder import release_all

    monkeypatch.chdir(tmp_path)
    (cfg,) = check_command_line("train", [*LANE, "run_name=R", "train.eval_episodes=0"])
    hydra = SimpleNamespace(runtime=SimpleNamespace(output_dir=str(tmp_path / "runs" / "R")), mode=None)
    monkeypatch.setattr(train_main.HydraConfig, "get", staticmethod(lambda: hydra))

    def refuses(cfg, ckpt_dir, run_dir, **_):
        assert (ckpt_dir / "config.yaml").is_file()
        raise ConfigError("agent.init_from='x': checkpoint 'x' was trained on env 'lane_keeping', not 'left_turn'")

    real = train.registry.trainer_of
    monkeypatch.setattr(train.registry, "trainer_of", lambda kind: refuses if kind == "ppo" else real(kind))
    try:
        with pytest.raises(ConfigError, match="was trained on env"):
            train_main.train(cfg)
    finally:
        release_all()
    assert not (tmp_path / "checkpoints").exists()


# ------------------------------------------------------------------------------------------------ Ctrl-C during cloning
def test_ctrl_c_while_cloning_says_what_was_kept(monkeypatch, capsys):
    """Ctrl-C during ppo_turn's cloning step exited 130 without a word."""
    from omegaconf import OmegaConf

    import train.ppo
    from agents.ppo import PPOParams
    from conf.check import check_command_line

    (cfg,) = check_command_line("train", ["agent=ppo_turn", "agent.init_episodes=4"])
    params = PPOParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
    stack = train.ppo._Stack(*[OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)],
                             params)
    closed = []

    class Env:
        def close(self):
            closed.append(True)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(train.ppo._Stack, "batched", lambda self: Env())
    monkeypatch.setattr(train.ppo, "pretrain_from_teacher", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train.ppo.clone_teacher(None, stack, "left_turn")
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("[train] interrupted while cloning gap_acceptance (") and "nothing was kept" in line \
        and "no latest.zip to resume" in line, line
    assert closed == [True]  # the demonstration env is closed on the way out


# -------------------------------------------------------------------------------------------- DAgger resumes at a round
def dagger_cfg(*extra: str):
    from hydra import compose, initialize_config_module

    with initialize_config_module("conf", version_base="1.3"):
        return compose("train", overrides=["agent=dagger_turn", "agent.rounds=3", "agent.round_episodes=2",
                                           "agent.n_envs=2", "agent.extractor=mlp", "agent.fit_epochs=1",
                                           "agent.go_threshold=0.8", "train.eval_n=2", "train.progress_bar=false",
                                           "run_name=D", *extra])


def dagger_run(tmp_path: Path, name: str, *extra: str, stop_at: int | None = None, monkeypatch=None,
               stop_in: str = "fit"):
    """A tiny DAgger run into ``tmp_path/name``; with ``stop_at``, Ctrl-C in that round's ``stop_in``: ``"fit"``,
    or ``"save_round"`` (after the round was logged to TensorBoard, before latest.zip holds it)."""
    import torch
    from omegaconf import OmegaConf

    import train.dagger

    cfg = dagger_cfg(*extra)
    ckpt, run_dir = tmp_path / name / "ckpt", tmp_path / name / "run"
    ckpt.mkdir(parents=True, exist_ok=True)
    (ckpt / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    if stop_at is not None:
        call, calls = getattr(train.dagger, stop_in), []

        def interrupted(*a, **k):
            calls.append(1)
            if len(calls) > stop_at:
                raise KeyboardInterrupt
            return call(*a, **k)
        monkeypatch.setattr(train.dagger, stop_in, interrupted)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return train.dagger.train_dagger(cfg, ckpt, run_dir)
    finally:
        torch.set_num_threads(threads)
        if monkeypatch is not None:
            monkeypatch.undo()


def test_the_aggregate_round_trips_exactly():
    import numpy as np

    from train.dagger import Round, pack_rounds, unpack_rounds

    rng = np.random.default_rng(0)
    data = Round(obs=[{"turn": rng.normal(size=6).astype(np.float32), "intent": rng.normal(size=(2, 3))}
                      for _ in range(5)], labels=[0, 1, 1, 0, 1], returns=list(rng.normal(size=5)))
    back = unpack_rounds(pack_rounds(data))
    assert list(back.obs[0]) == ["turn", "intent"] and len(back.obs) == 5
    for a, b in zip(data.obs, back.obs):
        assert all(np.array_equal(a[k], b[k]) and a[k].dtype == b[k].dtype for k in a)
    assert np.array_equal(np.array(back.labels), np.array(data.labels)) and back.returns == data.returns
    assert back.targets == []  # no P(GO) targets (agent.targets=labels)
    data.targets = list(rng.uniform(size=5))  # agent.targets=go_safe keeps them beside the labels
    assert unpack_rounds(pack_rounds(data)).targets == data.targets


@pytest.mark.slow  # three tiny DAgger runs (~20 CPU-s)
def test_dagger_stopped_then_resumed_ends_with_the_uninterrupted_student(tmp_path, monkeypatch, capsys):
    """a stopped DAgger run restarted at round 0, overwriting best.zip, latest.zip and rounds.csv, and its
    message named a latest.zip that might not exist. Now each finished round is in latest.zip; resumed, the run
    redoes only the round that was cut short and ends with the same student, bit for bit, and the same rows."""
    import csv

    import torch

    from agents.checkpoint import load_sb3

    whole = dagger_run(tmp_path, "whole")
    with pytest.raises(KeyboardInterrupt):
        dagger_run(tmp_path, "cut", stop_at=0, monkeypatch=monkeypatch)  # in round 0: nothing kept, and said so
    assert "before any round finished: nothing was kept (no latest.zip)" in capsys.readouterr().err
    assert not (tmp_path / "cut" / "ckpt" / "latest.zip").exists()
    with pytest.raises(KeyboardInterrupt):  # round 2 logged, not saved: its TensorBoard points are redone
        dagger_run(tmp_path, "cut", "train.overwrite=true", stop_at=2, monkeypatch=monkeypatch, stop_in="save_round")
    err = capsys.readouterr().err
    assert "interrupted in round 2: rounds 0..1 are kept in" in err and "train.resume=true" in err, err
    cut = tmp_path / "cut" / "ckpt"
    best = (cut / "best.zip").read_bytes()
    resumed = dagger_run(tmp_path, "cut", "train.resume=true")
    assert "resuming" in capsys.readouterr().out
    a, b = (load_sb3(p, device="cpu").policy.state_dict() for p in (whole, resumed))
    assert all(torch.equal(a[k], b[k]) for k in a), "the same student"
    # raw readers of the event files (not only TensorBoard, which honours purge_step) see each round once
    assert _raw_dagger_steps(tmp_path / "cut") == _raw_dagger_steps(tmp_path / "whole") != []

    def rows(path):
        with open(path) as f:
            return [{k: v for k, v in r.items() if k not in ("wall_s", "label_s", "fit_s")} for r in csv.DictReader(f)]
    assert rows(cut / "rounds.csv") == rows(tmp_path / "whole" / "ckpt" / "rounds.csv")
    assert len(rows(cut / "rounds.csv")) == 3
    assert best != b"" and (cut / "best.zip").is_file()


def _raw_dagger_steps(root: Path) -> list[int]:
    """The dagger/agreement steps in ``root``'s event files themselves, sorted (duplicates kept)."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    return sorted(e.step for path in (root / "run" / "tb").glob("*/events.*") for e in EventFileLoader(str(path)).Load()
                  for v in e.summary.value if v.tag == "dagger/agreement")


def test_a_dagger_checkpoint_without_rounds_is_not_resumed(tmp_path):
    """A latest.zip written before DAgger saved its rounds (or any PPO zip) is refused in one line."""
    from av_gym.errors import ConfigError

    ckpt = tmp_path / "old" / "ckpt"
    ckpt.mkdir(parents=True)
    shutil.copy(REF / "dagger_turn" / "model.zip", ckpt / "latest.zip")
    with pytest.raises(ConfigError, match=r"latest.zip holds no DAgger rounds .* agent.init_from="):
        dagger_run(tmp_path, "old", "train.resume=true")


# ---------------------------------------------------------------------------------------- generated files written whole
@pytest.fixture
def results_copy(tmp_path):
    """Two result folders of docs/results (one per scenario) and a README quoting the block."""
    root = tmp_path / "results"
    for name in ("left_turn_dagger_turn_aeb", "lane_keeping_A_pid"):
        shutil.copytree(ROOT / "docs" / "results" / name, root / name)
    # each agent's first 100 episodes, in the file's order: the page's bootstrap over 5 x 1,000 rows took ~1 s a call,
    # and what these tests check is how the files are written, not the numbers
    csv_file = root / "left_turn_dagger_turn_aeb" / "results.csv"
    header, *lines = csv_file.read_text().splitlines(keepends=True)
    per_agent: dict[str, list[str]] = {}
    for line in lines:
        per_agent.setdefault(line.split(",", 1)[0], []).append(line)
    assert len(per_agent) == 5 and all(len(rows) == 1000 for rows in per_agent.values())
    kept = {line for rows in per_agent.values() for line in rows[:100]}
    csv_file.write_text(header + "".join(line for line in lines if line in kept))
    from eval.results_page import BEGIN, END, PAGE_HEAD

    (tmp_path / "README.md").write_text("# title\n\n" + BEGIN + "\nold\n" + END + "\n\nthe rest\n" * 2000)
    (tmp_path / "page.md").write_text(PAGE_HEAD + "old page\n")  # a page the tool wrote: it may replace it
    return root


def results_page(argv: list[str], capsys) -> tuple[int, list[str]]:
    from eval.results_page import main

    code = main(argv)
    return code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


@pytest.mark.parametrize("how", ["fsync", "write"])
def test_the_results_page_and_readme_on_a_full_disk_stay_whole(how, results_copy, tmp_path, monkeypatch, capsys):
    """under a file-size limit README.md was cut to 16,384 of 43,299 bytes, with a traceback. The page and
    the README's block are written together, each whole, or neither."""
    from tests.test_reliability import fill_the_disk

    before = snapshot(tmp_path)
    fill_the_disk(monkeypatch, how)
    code, err = results_page(["--results", str(results_copy), "--out", str(tmp_path / "page.md"), "--readme",
                              str(tmp_path / "README.md")], capsys)
    assert code == 2 and len(err) == 1 and "No space left on device (the previous versions are intact)" in err[0], err
    assert snapshot(tmp_path) == before
    monkeypatch.undo()
    code, err = results_page(["--results", str(results_copy), "--out", str(tmp_path / "page.md"), "--readme",
                              str(tmp_path / "README.md")], capsys)
    assert code == 0 and "left_turn_dagger_turn_aeb" in (tmp_path / "README.md").read_text()
    assert (tmp_path / "README.md").read_text().endswith("the rest\n")


@pytest.mark.parametrize("damage, needle", [
    # a torn results.csv was a TypeError in _number
    (lambda f: f.write_text(f.read_text()[:3000]), "has 11 of 21 fields: torn or edited by hand?"),
    (lambda f: f.write_text(f.read_text().splitlines()[0] + "\n"), "has no episodes"),
    (lambda f: (f.parent / "meta.json").write_text("{not json"), "meta.json is not valid JSON"),
])
@pytest.mark.parametrize("check", [True, False])
def test_a_torn_results_file_is_one_line(damage, needle, check, results_copy, tmp_path, capsys):
    damage(results_copy / "left_turn_dagger_turn_aeb" / "results.csv")
    before = snapshot(tmp_path)
    code, err = results_page(["--results", str(results_copy), "--out", str(tmp_path / "page.md"),
                              *(["--check"] if check else [])], capsys)
    assert code == 2 and len(err) == 1 and needle in err[0], err
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("flag", ["--out", "--readme"])
def test_a_results_page_path_under_a_file_is_one_line(flag, results_copy, tmp_path, capsys):
    """``--out README.md/x`` was a NotADirectoryError traceback."""
    target = tmp_path / "README.md" / "x"
    code, err = results_page(["--results", str(results_copy), flag, str(target)], capsys)
    assert code == 2 and len(err) == 1 and f"{flag}={target}: " in err[0] and "is a file, not a folder" in err[0], err


@pytest.mark.parametrize("how", ["fsync", "savefig"])
def test_ccftap_on_a_full_disk_is_one_line_and_no_empty_png(how, tmp_path, monkeypatch, capsys):
    """``python -m eval.ccftap --out <a full disk>`` gave 3 tracebacks (53 lines) and an empty grid.png.
    A previous grid.png stays whole; a new one is never left empty or half-written."""
    import matplotlib.figure

    import av_gym.atomic
    from eval.ccftap import main

    out = tmp_path / "cc"
    out.mkdir()
    (out / "grid.png").write_bytes(b"the previous grid")
    if how == "fsync":
        monkeypatch.setattr(av_gym.atomic.os, "fsync", no_space)
    else:
        def half(self, path, *a, **k):
            Path(path).write_bytes(b"\x89PNG half")
            no_space()
        monkeypatch.setattr(matplotlib.figure.Figure, "savefig", half)
    code = main(["--ego", "[20]", "--target", "[60]", "--dts", "[0]", "--workers", "1", "--variants", "[none]",
                 "--plot-case", "[20,60,0]", "--out", str(out), "--overwrite"])  # the previous grid may be replaced
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and err[0].startswith("error: --out: cannot write ") and \
        "No space left on device" in err[0], err
    assert (out / "grid.png").read_bytes() == b"the previous grid"
    assert sorted(p.name for p in out.iterdir()) == (["grid.png"] if how == "fsync" else
                                                     ["grid.png", "results.csv", "results.md"])


# ---------------------------------------------------------------------------------------------- DAgger's counts bounded
@pytest.mark.parametrize("argv, needle", [
    (["agent.rounds=1000000000"], "agent.rounds must be an integer in [1, 100], got 1000000000"),
    (["agent.round_episodes=1e9"], "agent.round_episodes must be an integer in [1, 100000]"),
    (["agent.rounds=100", "agent.round_episodes=5000"], "agent.rounds x agent.round_episodes must be at most "
                                                         "100,000 episodes"),
])
def test_dagger_counts_have_upper_bounds(argv, needle, tmp_path, monkeypatch, capsys):
    """``agent.rounds=1000000000`` was accepted and ran without end, its label set growing."""
    from tests.test_bad_input import check_line

    monkeypatch.chdir(tmp_path)
    line = check_line("train", ["agent=dagger_turn", *argv], monkeypatch, capsys)
    assert needle in line, line
    assert not any(tmp_path.iterdir())


def test_the_dagger_bounds_admit_the_shipped_students():
    from conf.check import check_command_line

    for agent in ("dagger_turn", "dagger_turn_perceived"):
        assert check_command_line("train", [f"agent={agent}", "agent.rounds=8", "agent.round_episodes=192"])


# ------------------------------------------------------------------------------------------------------------- messages
@pytest.mark.parametrize("sensors, needle", [
    ({"name": "nosuch"}, "sensors.name='nosuch' is not a sensors preset and the section names no sensor; give a "
                         "preset (["),
    ({"detector": "high"}, "sensors.detector must be a mapping of the detector sensor's parameters ({} for its "
                           "defaults), got 'high'"),
    ({"name": "truth", "keep_state": False}, "sensors=truth names no sensor and drops the simulator's state"),
])
def test_sensor_sections_that_give_nothing_say_why(sensors, needle):
    """``sensors={"name": "nosuch"}`` said the stack "removes the privileged state"; ``detector="high"``
    raised TypeError, not ValueError."""
    import gymnasium as gym

    import av_gym  # noqa: F401 - registers the ids

    with pytest.raises(ValueError) as err:
        gym.make("av_gym/UnprotectedLeftTurn-v0", sensors=sensors)
    assert needle in str(err.value), str(err.value)


def test_a_checkpoint_without_config_yaml_is_not_told_to_see_it(tmp_path):
    """a checkpoint folder without config.yaml was told to "see its config.yaml"."""
    from agents.ppo import PPOAgent
    from av_gym.errors import ConfigError
    from av_gym.make import make_env

    (tmp_path / "bare").mkdir()
    shutil.copy(REF / "ppo_turn" / "model.zip", tmp_path / "bare" / "model.zip")
    env = make_env({"name": "left_turn"}, {"name": "truth"}, None)
    try:
        with pytest.raises(ConfigError) as err:
            PPOAgent.load(tmp_path / "bare" / "model.zip", env)
    finally:
        env.close()
    assert "see its config.yaml" not in str(err.value)
    assert "it has no config.yaml beside it saying which sensors preset and env settings it was trained with" in \
        str(err.value)


def test_a_zip_with_a_garbage_policy_is_one_whole_line_without_torch_advice(tmp_path):
    """a zip with a garbage policy.pth got torch's message cut mid-sentence, suggesting weights_only=False
    (which would run whatever the file holds)."""
    import zipfile

    from agents.checkpoint import load_sb3
    from agents.ppo import PPOAgent
    from av_gym.errors import ConfigError

    # Seeded garbage payloads that torch's unpickler trips on in different ways (with torch 2.13: UnpicklingError,
    # IndexError, UnicodeDecodeError, KeyError; 1 in 12 random payloads is not an UnpicklingError): each must give
    # the same line.
    for seed in (0, 17, 54, 62):
        bad = tmp_path / f"model_{seed}.zip"
        garbage = np.random.default_rng(seed).bytes(500)
        with zipfile.ZipFile(REF / "ppo_turn" / "model.zip") as z, zipfile.ZipFile(bad, "w") as out:
            for name in z.namelist():
                out.writestr(name, garbage if name == "policy.pth" else z.read(name))
        for load in (lambda: load_sb3(bad, device="cpu"), lambda: PPOAgent.load(bad, None)):
            with pytest.raises(ConfigError) as err:
                load()
            text = str(err.value)
            assert "weights_only" not in text and "\n" not in text and text.endswith("re-copy it or retrain"), text
            assert "a tensor member (policy.pth: the weights) is not one torch reads as plain tensors" in text, text


def test_a_long_message_ends_at_a_whole_sentence():
    from agents.checkpoint import _one_line

    text = _one_line(ValueError("First sentence here. " * 5 + "x" * 300))
    assert text.endswith("here.") and len(text) <= 200


# ------------------------------------------------------------------------------------------ make_vec's num_envs
@pytest.mark.parametrize("num_envs", [0, -1, 10**9, 2.5, True])
def test_make_vec_takes_an_integer_number_of_envs_in_its_bounds(num_envs):
    """0 and -1 failed deep in numpy, 1e9 asked for 179 GiB, 2.5 passed: one ValueError naming the field. (With
    ``vectorization_mode="sync"`` or ``"async"`` Gymnasium's own classes take num_envs before any av_gym code runs.)"""
    import gymnasium as gym

    import av_gym  # noqa: F401 - registers the ids

    with pytest.raises(ValueError, match=r"num_envs must be an integer in \[1, 4096\] \(the batched engine's rows\), "
                                         rf"got {num_envs!r}"):
        gym.make_vec("av_gym/UnprotectedLeftTurn-v0", num_envs=num_envs, sensors="turn_truth")


@pytest.mark.slow  # a real python -m eval process (its imports and an episode: ~7 CPU-s), for the helper's lock
def test_a_command_line_that_passes_the_check_in_the_test_process_still_runs(tmp_path):
    """``tests/conftest.py: cli`` runs the check in pytest's process first; the out_dir lock it took is released,
    so the command itself is not refused as "another evaluation"."""
    from tests.conftest import cli

    res = cli("eval", "agents=[always_proceed]", "episodes=1", "out_dir=X", "progress_bar=false", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "X").iterdir()) == ["meta.json", "results.csv", "results.md"]
