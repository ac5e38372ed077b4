"""The command line and faults: what a 150-case probe broke, one test each. Bounds on every value that
sets a loop count, an allocation or a time limit; seeds numpy can take; run folders owned by one run; writes that
stay consistent on a full disk; signals; side tools; a sweep that finishes what it can.

Most cases run the command-line check in this process (what ``python -m train|eval`` runs before Hydra makes any
folder); a few run the whole command in a subprocess, for what only the job can find."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_bad_input import check_line

ROOT = Path(__file__).resolve().parents[1]


def run(argv: list[str], cwd: Path, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    """``python <argv>`` with this checkout first on the path, in ``cwd``."""
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout, **kw)


def one_error_line(proc: subprocess.CompletedProcess) -> str:
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), \
        (proc.returncode, proc.stderr[-2000:])
    return lines[0]


# ----------------------------------------------------------------------------------------------------- bounds
@pytest.mark.parametrize("module, argv, needle", [
    # seeds numpy's legacy RandomState (SB3's set_random_seed) can take, also inside a -m sweep
    ("train", ["agent=ppo", "env=lane_keeping", "sensors=gnss_imu", "seed=4294967296"], "seed must be an integer in [0, 2147483647]"),
    pytest.param("train", ["agent=ppo", "env=lane_keeping", "sensors=gnss_imu", "seed=2**70"], "seed must be an integer",
                 marks=pytest.mark.slow),  # the bound above again (~0.3 s of Hydra a case), as an expression
    ("train", ["-m", "agent=ppo", "env=lane_keeping", "sensors=gnss_imu", "seed=0,4294967296"], "seed must be an integer in [0, 2147483647]"),
    ("train", ["train.eval_seed=4294967296"], "train.eval_seed must be an integer in [0, 2147483647]"),
    ("eval", ["seed=4294967296"], "seed must be an integer in [0, 2147483647]"),
    ("eval", ["-m", "seed=1,99999999999"], "seed must be an integer in [0, 2147483647]"),
    ("eval", ["episodes=100000000000"], "with 100000000000 episodes leaves split 'validation'"),
    # values that hung (a catch-up loop or a Poisson draw per unit, or an episode of ~forever)
    ("eval", ["sensors=gnss_imu", "sensors.gnss.rate_hz=1e9"], "sensors.gnss.rate_hz must be a number in (0, 1000]"),
    # every sensor's rate_hz is one Params bound (gnss above, fast); the other three sensors' are slow
    *[pytest.param("eval", [f"sensors={s}", f"sensors.{s}.rate_hz=1e9"], f"sensors.{s}.rate_hz must be a number in (0, 1000]",
                   marks=pytest.mark.slow) for s in ("cameras", "lidar", "detector")],
    ("eval", ["sensors=detector", "sensors.detector.clutter_rate=1e9"], "sensors.detector.clutter_rate must be a number in [0, 100]"),
    ("eval", ["env.policy_frequency=1000000000", "env.simulation_frequency=1000000000"], "env.policy_frequency must be an integer in [10, 1000]"),
    ("eval", ["env.simulation_frequency=1000000000"], "env.simulation_frequency must be an integer in [1, 1000]"),
    ("eval", ["env.mode=ccftap", "env.ccftap.dt=1e9"], "env.ccftap.dt must be a number in [-30, 30]"),
    ("eval", ["env.mode=ccftap", "env.ccftap.ego_speed_kmh=1e-9"], "env.ccftap.ego_speed_kmh must be a number in [1, 100]"),
    ("eval", ["env.duration=1e9"], "env.duration must be a number in (0, 600]"),
    ("eval", ["env=lane_keeping", "env.time_limit=1e9"], "env.time_limit must be a number in (0, 3600]"),
    ("eval", ["env=lane_keeping", "env.target_speed_kmh=1e-9"], "env.target_speed_kmh must be a number in [1, 200]"),
    # allocations of GiBs
    ("eval", ["sensors=cameras", "sensors.cameras.height=10000", "sensors.cameras.width=10000"], "sensors.cameras.height must be an integer in [2, 2160]"),
    ("eval", ["sensors=cameras", "sensors.cameras.height=2000", "sensors.cameras.width=3000"], "rendered pixels per camera"),
    ("eval", ["sensors=lidar", "sensors.lidar.beams=1e8"], "sensors.lidar.beams must be an integer"),
    ("eval", ["sensors=lidar", "sensors.lidar.beams=100000000"], "sensors.lidar.beams must be an integer in [1, 32768]"),
    ("eval", ["sensors=lidar", "sensors.lidar.beams=32768", "sensors.lidar.elevations_deg=[0,1,2,3,4,5,6,7,8]"], "rays per scan"),
    ("eval", ["sensors=detector", "sensors.detector.max_objects=100000000"], "sensors.detector.max_objects must be an integer in [1, 256]"),
    ("train", ["agent.n_envs=100000000"], "agent.n_envs must be an integer in [1, 4096]"),
    ("train", ["agent=ppo", "env=lane_keeping", "sensors=gnss_imu", "agent.n_envs=500"], "agent.n_envs must be at most 64 with agent.vec_env=subproc"),
    ("train", ["train.eval_n_envs=1000"], "train.eval_n_envs must be an integer in [1, 64]"),
    ("eval", ["n_envs=100"], "n_envs must be at most 64 with vec_env=subproc"),
    ("eval", ["n_envs=100000", "vec_env=batched"], "n_envs must be an integer in [1, 1024]"),
])
def test_values_that_hung_or_asked_for_gibibytes_are_one_line(module, argv, needle, monkeypatch, capsys, tmp_path):
    monkeypatch.chdir(tmp_path)
    line = check_line(module, argv, monkeypatch, capsys)
    assert needle in line, line
    assert not any(tmp_path.iterdir())  # nothing written


@pytest.mark.slow  # composes every preset and PPO agent config, ~20 s on a busy machine
def test_the_bounds_admit_every_shipped_config(monkeypatch, capsys, tmp_path):
    """Every shipped sensors preset and agent config still passes (a bound is not a new default)."""
    from conf.check import check_command_line, options

    monkeypatch.chdir(tmp_path)
    for sensors in options("sensors"):
        env = "lane_keeping" if sensors in ("camera_centre", "cameras", "lane_localized", "gnss_raw") else "left_turn"
        assert check_command_line("eval", [f"env={env}", f"sensors={sensors}"])
    for agent in ("ppo_turn", "ppo_turn_perceived", "ppo_turn_shielded"):
        assert check_command_line("train", [f"agent={agent}"])


@pytest.mark.parametrize("name", [".", "..", "...", "a/b", "../up"])
@pytest.mark.parametrize("module", ["train"])
def test_run_name_cannot_leave_its_folder(module, name, monkeypatch, capsys, tmp_path):
    """``run_name=..`` wrote .hydra/, logs and config.yaml into the repo root."""
    monkeypatch.chdir(tmp_path)
    line = check_line(module, [f"run_name={name}"], monkeypatch, capsys)
    assert "run_name must be a folder name" in line, line
    assert not any(tmp_path.iterdir())


# --------------------------------------------------------------------------------------------- run folders owned
LANE = ["agent=ppo", "env=lane_keeping", "sensors=gnss_imu"]


@pytest.fixture
def released():
    """Whatever a test's command-line check claimed is released afterwards (the check holds the lock for the
    life of the process, which here is pytest's)."""
    from train.run_folder import release_all

    yield
    release_all()


def a_run(tmp_path: Path, name: str = "R", argv: list[str] = LANE, latest: bool = True) -> Path:
    """checkpoints/<name>/ as a run trained with ``argv`` leaves it: config.yaml (composed as train composes it),
    latest.zip, model.zip (placeholders: the checks read config.yaml and test that the zip exists)."""
    from omegaconf import OmegaConf

    from conf.check import check_command_line

    (cfg,) = check_command_line("train", [*argv, f"run_name={name}"])
    ckpt = tmp_path / "checkpoints" / name
    ckpt.mkdir(parents=True)
    (ckpt / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    for zip_ in ("latest.zip", "model.zip") if latest else ("model.zip",):
        (ckpt / zip_).write_bytes(b"PK placeholder")
    return ckpt


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("argv, needle", [
    ([*LANE, "run_name=R"], "checkpoints/R already holds a run (config.yaml, latest.zip, model.zip)"),  # row 3
    (["run_name=R", "train.resume=true"], "train.resume=true: env.name is 'left_turn' here but 'lane_keeping' in "),  # row 2
    ([*LANE, "run_name=R", "train.resume=true", "sensors.gnss.sigma=3"], "sensors.gnss.sigma is 3 here but 1.5"),
    ([*LANE, "run_name=nosuchrun", "train.resume=true"], "train.resume=true but checkpoints/nosuchrun/latest.zip does "
                                                         "not exist"),  # row 12
])
def test_a_run_that_is_not_ours_is_refused_with_nothing_written(argv, needle, tmp_path, monkeypatch, capsys, released):
    monkeypatch.chdir(tmp_path)
    a_run(tmp_path)
    before = snapshot(tmp_path)
    line = check_line("train", argv, monkeypatch, capsys)
    assert needle in line, line
    assert snapshot(tmp_path) == before  # config.yaml not rewritten, no folder for nosuchrun, no lock left
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["R"]


def test_runs_folder_of_another_run_is_refused(tmp_path, monkeypatch, capsys, released):
    """Its TensorBoard curves would go into the same folder as the first run's (a run's log folder: Hydra's
    .hydra/config.yaml of a training job, its tb/)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs" / "R" / "tb").mkdir(parents=True)
    (tmp_path / "runs" / "R" / ".hydra").mkdir()
    (tmp_path / "runs" / "R" / ".hydra" / "config.yaml").write_text("env: {name: lane_keeping}\nagent: {name: ppo}\n")
    line = check_line("train", [*LANE, "run_name=R"], monkeypatch, capsys)
    assert "runs/R already holds a run's logs (.hydra, tb)" in line and "train.overwrite=true" in line, line
    assert not (tmp_path / "checkpoints").exists()


def test_resume_and_overwrite_are_allowed_and_hold_the_lock(tmp_path, monkeypatch, released):
    from train import __main__ as train_main
    from train.run_folder import release_all

    monkeypatch.chdir(tmp_path)
    ckpt = a_run(tmp_path)
    (ckpt / "model.zip").unlink()  # an interrupted run (a finished one is not resumed: tests/test_nothing_lost.py)
    for extra in (["train.resume=true"], ["train.overwrite=true"], ["train.resume=true", "agent.total_timesteps=99"]):
        monkeypatch.setattr(sys, "argv", ["train", *LANE, "run_name=R", *extra])
        train_main._check_command_line()
        assert (ckpt / ".lock").read_text().strip() == str(os.getpid())
        release_all()
        assert not (ckpt / ".lock").exists()


def test_a_second_process_on_the_same_run_is_refused(tmp_path, monkeypatch, capsys, released):
    """Two at once with the same run_name. Another process's flock (taken here on a separate open file
    description, which flock treats as another owner) refuses the second, resume or not."""
    import fcntl

    monkeypatch.chdir(tmp_path)
    ckpt = a_run(tmp_path)
    (ckpt / "model.zip").unlink()  # still training: no final model yet
    fd = os.open(ckpt / ".lock", os.O_RDWR | os.O_CREAT)
    os.write(fd, b"4242\n")
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    try:
        line = check_line("train", [*LANE, "run_name=R", "train.resume=true"], monkeypatch, capsys)
        assert "another process (pid 4242) is training this run" in line, line
    finally:
        os.close(fd)
    assert (ckpt / ".lock").exists()  # the holder's file is left to the holder


@pytest.mark.slow  # three runs of python -m train (a rule-based agent: nothing trained)
def test_train_twice_refuses_then_overwrite_replaces(tmp_path):
    argv = ["-m", "train", "agent=always_proceed", "train.eval_episodes=0", "run_name=R"]
    first = run(argv, tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    config = (tmp_path / "checkpoints" / "R" / "config.yaml").read_bytes()
    assert "already holds a run" in one_error_line(run([*argv, "env.duration=30"], tmp_path))
    assert (tmp_path / "checkpoints" / "R" / "config.yaml").read_bytes() == config
    third = run([*argv, "env.duration=30", "train.overwrite=true"], tmp_path)
    assert third.returncode == 0, third.stderr[-2000:]
    assert b"duration: 30" in (tmp_path / "checkpoints" / "R" / "config.yaml").read_bytes()
    assert not list((tmp_path / "checkpoints").rglob(".lock"))


# ------------------------------------------------------------------------------------------- a full disk tears nothing
def no_space(*_args, **_kw):
    import errno

    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


class HalfWritten:
    """A file whose writes put half their text on disk, then fail as a full disk does."""

    def __init__(self, f):
        self.f = f

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.f.close()

    def write(self, text):
        self.f.write(text[: len(text) // 2])
        self.f.flush()
        no_space()

    def __getattr__(self, name):
        return getattr(self.f, name)


def fill_the_disk(monkeypatch, how: str) -> None:
    """``fsync``: the data cannot be flushed; ``write``: half of it reaches the file, then ENOSPC."""
    import builtins

    import av_gym.atomic

    if how == "fsync":
        monkeypatch.setattr(av_gym.atomic.os, "fsync", no_space)
    else:
        monkeypatch.setattr(av_gym.atomic, "open", lambda *a, **k: HalfWritten(builtins.open(*a, **k)),
                            raising=False)


def rows(n: int, value: float = 0.0) -> list[dict]:
    return [{"agent": "a", "seed": i, "collision": i % 2, "success": 1 - i % 2, "return": value + i} for i in range(n)]


@pytest.mark.parametrize("how", ["fsync", "write"])
def test_results_on_a_full_disk_stay_whole(how, tmp_path, monkeypatch, capsys):
    """``results.csv`` was torn at row 10 of 20 and results.md stale; now both stay as they were, no temporary
    file is left, and the command says so in one line."""
    from av_gym.errors import run_cli
    from eval.report import write_results

    write_results(rows(10), tmp_path, "left_turn", "first")
    before = snapshot(tmp_path)
    fill_the_disk(monkeypatch, how)
    with pytest.raises(SystemExit) as exit_:
        run_cli(write_results, rows(20, 5.0), tmp_path, "left_turn", "second")
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_.value.code == 2 and len(err) == 1, err
    assert err[0].startswith("error: out_dir: cannot write ") and "No space left on device" in err[0], err
    assert "previous versions are intact" in err[0]
    assert snapshot(tmp_path) == before  # the same two files, byte for byte: nothing torn, nothing left over


@pytest.fixture(scope="module")
def tiny_ppo():
    """A small SB3 PPO (CartPole): what a checkpoint holds is the same whatever the env."""
    import gymnasium as gym
    from stable_baselines3 import PPO

    return PPO("MlpPolicy", gym.make("CartPole-v1"), n_steps=64, batch_size=32, seed=0, device="cpu")


@pytest.mark.parametrize("how", ["fsync", "write", "save"])
def test_a_checkpoint_on_a_full_disk_keeps_the_last_pair(how, tiny_ppo, tmp_path, monkeypatch):
    """``latest.rng`` was replaced while latest.zip was not. The RNG states now live inside latest.zip (one
    file, one rename); a failed save leaves the previous zip, with its own states, and no temporary file."""
    import pickle
    import zipfile

    from av_gym.atomic import WriteFailed
    from train.callbacks import AtomicCheckpointCallback
    from train.checkpoint import RNG_MEMBER, load_rng_state

    callback = AtomicCheckpointCallback(tmp_path, every=1)
    callback.init_callback(tiny_ppo)
    callback._boundary = 64
    callback.save()
    before = snapshot(tmp_path)
    with zipfile.ZipFile(tmp_path / "latest.zip") as z:
        state = pickle.loads(z.read(RNG_MEMBER))
    assert set(state) >= {"python", "numpy", "torch", "logger"}
    if how == "save":  # SB3's own write fails half-way

        def save(self, path, *a, **k):
            Path(path).write_bytes(b"PK\x03\x04 half a zip")
            no_space()
        monkeypatch.setattr(type(tiny_ppo), "save", save)
    else:
        fill_the_disk(monkeypatch, how)
        if how == "write":  # the zip member is added through zipfile's own open: fail there too
            monkeypatch.setattr(zipfile.ZipFile, "writestr", lambda *a, **k: no_space())
    callback._boundary = 128
    with pytest.raises(WriteFailed, match=r"paths.checkpoints: cannot write .*latest.zip: No space left on device "
                                          r"\(the previous version is intact\)"):
        callback.save()
    monkeypatch.undo()
    assert snapshot(tmp_path) == before
    assert load_rng_state(tmp_path / "latest.zip")["numpy"][1].tolist() == state["numpy"][1].tolist()


# ---------------------------------------------------------------------------------------- signals and worker processes
def children(pid: int) -> set[int]:
    """Every descendant process of ``pid`` (Linux /proc)."""
    found, todo = set(), [pid]
    while todo:
        parent = todo.pop()
        for task in Path(f"/proc/{parent}/task").glob("*"):
            try:
                kids = {int(k) for k in (task / "children").read_text().split()}
            except OSError:
                continue
            todo += list(kids - found)
            found |= kids
    return found


def alive(pids: set[int]) -> set[int]:
    out = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            out.add(pid)
    return out


def _default_sigint() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Eval:
    """``python -m eval`` with 2 worker processes on a run that does not end, started and waited for until its
    progress bar shows ``episodes`` measured; its stderr is read as it comes (``err()``: without the bar)."""

    EVAL = ["-m", "eval", "agents=[always_proceed]", "episodes=100000", "n_envs=2", "progress_bar=true", "out_dir=out"]

    def __init__(self, tmp_path: Path, episodes: int = 4, argv: list[str] = EVAL, total: int = 100000):
        import re
        import threading
        import time

        env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
        self.total = total
        # SIGINT as in a terminal: a test run started in the background (nohup ... &, without job control) hands
        # its children SIGINT ignored, and a Ctrl-C test would then wait for an evaluation that never ends
        self.proc = subprocess.Popen([sys.executable, *argv], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)
        self.chunks: list[str] = []
        reader = threading.Thread(target=self._read, daemon=True)
        reader.start()
        deadline = time.time() + 150
        while time.time() < deadline:
            done = [int(n) for n in re.findall(rf"\| *(\d+)/{total}", "".join(self.chunks))]
            if done and max(done) >= episodes:
                break
            assert self.proc.poll() is None, self.err()
            time.sleep(0.2)
        self.workers = children(self.proc.pid)
        assert len(self.workers) >= 2, self.workers

    def _read(self) -> None:
        while True:
            chunk = self.proc.stderr.read(1)
            if not chunk:
                return
            self.chunks.append(chunk)

    def err(self) -> str:
        """stderr without the progress bar's redraws."""
        text = "".join(self.chunks).replace("\r", "\n")
        return "\n".join(line for line in text.splitlines() if line.strip() and f"/{self.total}" not in line)

    def wait(self) -> int:
        self.proc.stdout.read()
        rc = self.proc.wait(timeout=60)
        import time

        time.sleep(0.5)  # the reader's last bytes
        return rc


@pytest.mark.slow  # an evaluation with 2 worker processes, ~15-20 s
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and PR_SET_PDEATHSIG: Linux")
def test_sigterm_keeps_the_episodes_and_ends_the_workers(tmp_path):
    """SIGTERM (kill, timeout) used to end eval at once, rc 143, out_dir empty, workers orphaned."""
    import signal

    run_ = Eval(tmp_path)
    run_.proc.send_signal(signal.SIGTERM)
    rc, err = run_.wait(), run_.err()
    assert rc == 130, err[-3000:]
    assert "Traceback" not in err and "interrupted: the" in err, err[-3000:]
    lines = (tmp_path / "out" / "results.csv").read_text().splitlines()
    assert len(lines) > 4 and "(interrupted after" in (tmp_path / "out" / "results.md").read_text()
    assert not alive(run_.workers)


@pytest.mark.slow  # an evaluation with 2 worker processes, ~15-20 s
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and PR_SET_PDEATHSIG: Linux")
def test_workers_die_with_a_killed_parent(tmp_path):
    """After kill -9 of eval, its workers and the resource tracker lived on (~180 MB each)."""
    import signal
    import time

    run_ = Eval(tmp_path, episodes=1)
    assert len(run_.workers) >= 3  # 2 workers and multiprocessing's resource tracker
    run_.proc.send_signal(signal.SIGKILL)
    run_.wait()
    deadline = time.time() + 20
    while alive(run_.workers) and time.time() < deadline:
        time.sleep(0.2)
    assert not alive(run_.workers)


def ctrl_c_to_the_group(run_) -> None:
    """What a terminal's Ctrl-C does: SIGINT to the whole foreground group (the command and its workers)."""
    import signal

    for pid in {run_.proc.pid, *run_.workers}:
        try:
            os.kill(pid, signal.SIGINT)
        except ProcessLookupError:
            pass


@pytest.mark.slow  # an evaluation with 2 worker processes, ~15-20 s
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="process groups and /proc: Linux")
def test_ctrl_c_to_the_process_group_is_one_line_not_worker_tracebacks(tmp_path):
    """Ctrl-C reaches every process of the terminal's group; each worker printed its own traceback."""
    run_ = Eval(tmp_path)
    ctrl_c_to_the_group(run_)
    rc, err = run_.wait(), run_.err()
    assert rc == 130 and "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
    assert len(err.splitlines()) == 1 and "interrupted: the" in err, err
    assert (tmp_path / "out" / "results.csv").is_file() and not alive(run_.workers)


@pytest.mark.slow  # python -m train of a rule-based agent, its brief evaluation on 2 worker processes, ~20 s
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="process groups and /proc: Linux")
def test_ctrl_c_during_trains_brief_evaluation_is_one_line_and_keeps_its_rows(tmp_path):
    """74 stderr lines of worker tracebacks, and the brief evaluation's rows were not written."""
    run_ = Eval(tmp_path, argv=["-m", "train", "agent=always_proceed", "train.eval_episodes=1000",
                                "train.eval_n_envs=2", "run_name=R"], total=1000)
    ctrl_c_to_the_group(run_)
    rc, err = run_.wait(), run_.err()
    assert rc == 130 and "Traceback" not in err and "KeyboardInterrupt" not in err, err[-3000:]
    assert len(err.splitlines()) == 1 and "interrupted during the brief evaluation" in err, err
    assert len((tmp_path / "runs" / "R" / "results.csv").read_text().splitlines()) > 4
    assert not alive(run_.workers) and not (tmp_path / "checkpoints" / "R" / ".lock").exists()


# ------------------------------------------------------------------------------- a sweep finishes the cells it can
@pytest.mark.slow  # a 2-job eval sweep, ~30-100 s on 2 busy cores
def test_a_sweep_runs_every_cell_and_reports_the_failed_ones(tmp_path):
    """A job-time failure in the first cell used to abort the sweep; the good cell never ran. Here the
    checkpoint passes every check made before the sweep (a zip with SB3's members and good CRCs) and fails only
    when the job loads it."""
    import shutil
    import zipfile

    from agents.checkpoint import SB3_MEMBERS
    from tests.test_bad_input import REFERENCE

    shutil.copytree(REFERENCE, tmp_path / "bad")
    with zipfile.ZipFile(tmp_path / "bad" / "model.zip", "w") as z:
        for member in SB3_MEMBERS:
            z.writestr(member, b"{not what SB3 wrote")
    res = run(["-m", "eval", "-m", "agents=[bad],[always_proceed]", "episodes=2", "progress_bar=false"], tmp_path,
              timeout=400)
    errors = [line for line in res.stderr.splitlines() if line.startswith("error: ")]
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr[-3000:]
    assert len(errors) == 2 and errors[0].startswith("error: sweep job 0 (agents=[bad]") and \
        "cannot be loaded" in errors[0] and "1 sweep job(s) failed" in errors[1], errors
    (good,) = (tmp_path / "runs" / "multirun").glob("*/1/results.csv")  # the good cell ran and wrote its rows
    assert "always_proceed" in good.read_text()


# -------------------------------------------------------------------------------------------- the side tools' flags
@pytest.mark.parametrize("argv, needle", [
    (["-m", "eval.ccftap", "--ego", "abc"], "argument --ego: expected a list of numbers like [1,2], got 'abc'"),
    (["-m", "eval.ccftap", "--out", "README.md/x"], "argument --out=README.md/x: 'README.md' (part of 'README.md/x') "
                                                    "is a file, not a folder"),
    (["-m", "eval.ccftap", "--dts", "1e9"], "argument --dts: each value must be in [-30, 30], got '1e9'"),
    (["-m", "eval.ccftap", "--ego", "[0,15]"], "argument --ego: each value must be in [1, 100], got '0'"),
    (["-m", "eval.ccftap", "--workers", "0"], "argument --workers: expected an integer in [1, 64], got '0'"),
    (["-m", "eval.ccftap", "--seed", "4294967296"], "argument --seed: expected an integer in [0, 2147483647]"),
    (["-m", "eval.curves", "docs", "--out", "README.md/c.png"], "argument --out=README.md/c.png: 'README.md' is a "
                                                                "file, not a folder"),
    (["-m", "eval.curves", "README.md"], "argument tb_dirs: README.md is not a folder"),
    (["benchmarks/batched_speed.py", "--sizes", "0"], "argument --sizes: each value must be in [1, 4096], got '0'"),
])
def test_side_tools_refuse_bad_flags_in_one_line(argv, needle, monkeypatch, capsys):
    """These gave tracebacks. Run in this process from the checkout (README.md is a file there), as
    ``python <argv>`` would run them."""
    import runpy

    monkeypatch.chdir(ROOT)
    if argv[0] == "-m":
        monkeypatch.setattr(sys, "argv", [argv[1], *argv[2:]])
        # not imported yet, as under `python -m` (runpy warns when an earlier test left the module in sys.modules)
        monkeypatch.delitem(sys.modules, argv[1], raising=False)
        target = lambda: runpy.run_module(argv[1], run_name="__main__", alter_sys=False)  # noqa: E731
    else:
        monkeypatch.setattr(sys, "argv", argv)
        target = lambda: runpy.run_path(str(ROOT / argv[0]), run_name="__main__")  # noqa: E731
    with pytest.raises(SystemExit) as exit_:
        target()
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 2 and len(err) == 1 and err[0].startswith("error: "), err
    assert needle in err[0], err


# -------------------------------------------------------------------------------------------------------- messages
def test_an_empty_or_foreign_pilotnet_file_is_one_line_naming_it(tmp_path):
    import torch

    from agents.pilotnet import FORMAT, PilotNet, load_policy

    empty = tmp_path / "model.pt"
    empty.write_bytes(b"")
    with pytest.raises(ValueError) as err:
        load_policy(empty)
    assert str(err.value) == f"{empty} is empty (0 bytes): a copy or download that did not finish? Re-copy it or " \
                             f"retrain"
    state = PilotNet().state_dict()
    key = next(iter(state))
    state[key] = torch.zeros(7, *state[key].shape[1:])
    other = tmp_path / "other.pt"
    torch.save({"format": FORMAT, "state_dict": state, "preprocess": {"crop_top": 0}}, other)
    with pytest.raises(ValueError) as err:
        load_policy(other)
    expected = list(PilotNet().state_dict()[key].shape)
    assert str(err.value) == f"{other} holds weights of another network: {key!r} has shape {[7, *expected[1:]]}, " \
                             f"PilotNet expects {expected}"


def test_no_train_command_is_suggested_that_train_refuses(tmp_path, monkeypatch, capsys):
    """``agents=[pilotnet] env=left_turn`` suggested ``python -m train env=left_turn agent=pilotnet``."""
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", ["agents=[pilotnet]", "env=left_turn"], monkeypatch, capsys)
    assert "pilotnet drives ['lane_keeping'], not env=left_turn" in line and "python -m train" not in line, line


def test_ctrl_c_during_behaviour_cloning_says_what_is_kept(tmp_path, monkeypatch, capsys):
    """It exited 130 without a word."""
    import train.bc
    from agents.bc import PilotNetParams

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(train.bc, "collect_demos", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train.bc.train(PilotNetParams(), {}, {}, tmp_path / "run", tmp_path / "ckpt", log=lambda *_: None)
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["[bc] interrupted while collecting demonstrations: no model was saved yet"], err


def test_eval_does_not_write_over_an_evaluation(tmp_path, monkeypatch, capsys):
    """Eval silently replaced results.csv/results.md in an existing out_dir; now refused unless
    ``overwrite=true`` (the default out_dir is a new folder per run)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "results.csv").write_text("agent,seed\n")
    line = check_line("eval", ["out_dir=out", "agents=[always_proceed]"], monkeypatch, capsys)
    assert "out_dir=out already holds results.csv of an evaluation" in line and "overwrite=true" in line, line
    from conf.check import check_command_line

    assert check_command_line("eval", ["out_dir=out", "agents=[always_proceed]", "overwrite=true"])
    assert (tmp_path / "out" / "results.csv").read_text() == "agent,seed\n"


# ---------------------------------------------------------------------------------------- the mixed soak, quick form
@pytest.mark.slow  # 48 episodes over 16 configurations, each stack built once: ~1.5 CPU-minutes
def test_the_quick_mixed_soak_is_clean(tmp_path, monkeypatch, capsys):
    """benchmarks/soak.py --quick: no exception, no non-finite reward, no metric outside its kind's range."""
    import runpy

    monkeypatch.chdir(tmp_path)
    soak = runpy.run_path(str(ROOT / "benchmarks" / "soak.py"))
    assert soak["main"](["--quick", "--quiet", "--out", str(tmp_path / "soak.md")]) == 0, capsys.readouterr().out
    text = (tmp_path / "soak.md").read_text()
    assert "| exceptions | 0 | PASS (none) |" in text and "48 of 48" in text


@pytest.mark.parametrize("method", ["fork", "forkserver"])
def test_guarded_worker_lives_under_every_start_method(method):
    """A forkserver worker's OS parent is the forkserver, not multiprocessing's parent: the guard once took that
    for a dead parent and exited silently, so every SubprocVecEnv (SB3 starts its workers by forkserver) died."""
    import multiprocessing

    from _in_process import guarded_worker

    ctx = multiprocessing.get_context(method)
    queue = ctx.Queue()
    worker = ctx.Process(target=guarded_worker, args=(queue,))
    worker.start()
    worker.join(60)
    assert worker.exitcode == 0 and queue.get(timeout=5) == "alive"
