from __future__ import annotations

import sys

# Before any other import of this file: whether numpy came before the conftest (a plugin such as pytest-randomly
# imports it first; OpenBLAS then keeps its default threads, whatever is set below)
NUMPY_BEFORE_CONFTEST = "numpy" in sys.modules

import os  # noqa: E402
import subprocess  # noqa: E402
from importlib import resources  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

# `python -m train` / `python -m eval` in a subprocess started from another folder (tmp_path): an install puts only
# av_gym on sys.path, the harness packages are the checkout's (pyproject's pythonpath does this for pytest itself).
# A documented command runs without it (tests/test_documented_commands.py: _run), as a user runs it.
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(Path(__file__).resolve().parents[1]), *filter(None, [os.environ.get("PYTHONPATH")])])

# One OpenMP / BLAS thread per test process (torch, MKL, numpy's OpenBLAS), as `python -m train` runs torch
# (train.torch_threads=1); a user's own setting wins. Why: `pytest -n auto` already keeps every core busy with one
# worker each, and a second thread per process only spins waiting for a core. Measured (4 torch-heavy files, one
# process, the other core busy, load ~2.5): 134-140 CPU-s with the default 2 threads, 46-48 with one.
# Set here, before numpy is imported below (OpenBLAS reads it once, as numpy loads: pytest's own process, which runs
# the tests under -p no:xdist, kept OpenBLAS's default threads while numpy came first) and before anything imports
# torch: the xdist workers and every command a test starts inherit it.
# What tests/test_blas_threads.py may assert: only where this file chose the count (here, or in the pytest process
# that started this xdist worker: the marker is inherited with the count) and numpy loaded after this file began.
if "OMP_NUM_THREADS" not in os.environ:
    os.environ["OMP_NUM_THREADS"] = os.environ["AV_GYM_TESTS_SET_OMP"] = "1"
OMP_SET_HERE = os.environ.get("AV_GYM_TESTS_SET_OMP") == os.environ["OMP_NUM_THREADS"] and not NUMPY_BEFORE_CONFTEST
if "torch" in sys.modules:  # imported already (a plugin): the variable is read when torch loads
    sys.modules["torch"].set_num_threads(int(os.environ["OMP_NUM_THREADS"]))

import numpy as np  # noqa: E402  (after OMP_NUM_THREADS: see above)
import yaml  # noqa: E402


def conf(group: str, name: str) -> dict:
    """A config section exactly as shipped in conf/ (tests build envs the way the CLI does); a sensor without a
    conf/sensor/ yaml has its defaults in its Params (what conf/__init__.py stores in Hydra's ConfigStore)."""
    path = resources.files("conf") / group / f"{name}.yaml"
    if group == "sensor" and not path.is_file():
        from av_gym.registry import SENSORS

        return SENSORS.get(name).Params().as_dict()
    shipped = yaml.safe_load(path.read_text()) or {}
    if group == "env":  # conf/env/<name>.yaml holds only what differs from the scenario's Params
        from av_gym.registry import SCENARIOS

        shipped = {**SCENARIOS.get(name).Params().as_dict(), **{k: v for k, v in shipped.items() if k != "defaults"}}
    if group == "shield":  # conf/shield/aeb*.yaml: the variant's Params defaults (/aeb/<variant>), filled by the shield
        shipped.pop("defaults", None)
    return shipped


@pytest.fixture(autouse=True)
def _root_logging_restored():
    """A test that runs ``python -m eval`` / ``train`` in this process (``main()``) leaves Hydra's job logging on the
    root logger: a file handler into that test's folder, which a later test's log line (TensorBoard's, at INFO) then
    fails to open. Every test ends with the root logger's handlers and level as it found them."""
    import logging

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in [h for h in root.handlers if h not in handlers]:
        root.removeHandler(handler)
        handler.close()
    root.setLevel(level)


@pytest.fixture
def lane_cfg() -> dict:
    return conf("env", "lane_keeping")


@pytest.fixture
def turn_cfg() -> dict:
    return conf("env", "left_turn")


def ccftap_cfg(ego_kmh: float, target_kmh: float, dt: float, action: str = "discrete") -> dict:
    cfg = conf("env", "left_turn")
    cfg.update(mode="ccftap", action=action)
    cfg["ccftap"] = {"ego_speed_kmh": ego_kmh, "target_speed_kmh": target_kmh, "dt": dt}
    return cfg


def rollout(env, policy, seed: int, max_steps: int = 100_000):
    """Run one episode; returns (list of truth dicts, last info, terminated, truncated)."""
    obs, info = env.reset(seed=seed)
    policy.reset()
    truths = []
    for _ in range(max_steps):
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        truths.append(info["truth"])
        if terminated or truncated:
            return truths, info, terminated, truncated
    raise AssertionError("episode did not end")


def proceed_infos(env, seed: int = 0) -> list[dict]:
    """AlwaysProceed at the env's cruise set-point to the end of one episode; the info of every step."""
    from agents import AlwaysProceed

    policy = AlwaysProceed(env.unwrapped.cruise_action())
    obs, _ = env.reset(seed=seed)
    infos = []
    while True:
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        infos.append(info)
        if terminated or truncated:
            return infos


class Scripted:
    """A policy from a function of (step, obs)."""

    def __init__(self, fn):
        self.fn, self.k = fn, 0

    def reset(self):
        self.k = 0

    def act(self, obs):
        self.k += 1
        return self.fn(self.k - 1, obs)


@pytest.fixture
def make():
    # imported here, not at the top: pytest's own process under -n imports this file only to start the numba
    # warm-up (pytest_configure), and av_gym.make's imports (highway-env, gymnasium's envs) cost ~3 CPU-s first
    from av_gym.make import make_env

    return make_env


# A tiny PPO run: every budget at its smallest that still runs each part (a rollout, an update, a checkpoint, the
# periodic evaluation on 2 episodes, the brief evaluation on 2).
FAST_PPO = ["agent.total_timesteps=256", "agent.n_steps=64", "agent.batch_size=64", "agent.n_epochs=1",
            "agent.n_envs=1", "train.eval_episodes=2", "train.eval_n=2", "train.progress_bar=false"]


def run(module: str, *overrides: str, cwd: Path) -> subprocess.CompletedProcess:
    """``python -m <module> <overrides>`` in ``cwd``, as a user runs it."""
    return subprocess.run([sys.executable, "-m", module, *overrides], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


def cli(module: str, *overrides: str, cwd: Path) -> subprocess.CompletedProcess:
    """:func:`run`, for a command line that its command-line check may refuse: that check (what
    ``python -m <module>`` runs before Hydra, ``<module>/__main__.py: _check_command_line`` under
    :func:`av_gym.errors.run_cli`) runs in this process first, with the same argv and working directory, and a
    refusal comes back as the command's would (exit status 2, its stderr). Why: a Python process that imports
    torch, SB3 and highway-env costs ~4 s, most of a bad-input test; what passes the check runs for real."""
    import contextlib
    import importlib
    import io
    import os

    from av_gym.errors import run_cli

    entry = importlib.import_module(f"{module}.__main__")
    err, argv, here = io.StringIO(), sys.argv, os.getcwd()
    sys.argv = [f"{module}/__main__.py", *overrides]
    os.chdir(cwd)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            run_cli(entry._check_command_line)
    except SystemExit as exc:
        return subprocess.CompletedProcess([module, *overrides], exc.code, "", err.getvalue())
    finally:
        sys.argv = argv
        os.chdir(here)
        # a passing check locks the run or out_dir for its process, here pytest's: the command's own check takes it
        from eval.__main__ import OUT_DIRS
        from train.run_folder import release_all

        release_all()
        OUT_DIRS.release_all()
    return run(module, *overrides, cwd=cwd)


@pytest.fixture(scope="session")
def trained(tmp_path_factory, request):
    """One tiny PPO run of the default agent on the left turn per test session, shared by every test (and every
    xdist worker: the first to get here trains, under a file lock, the others read its output) that needs a trained
    checkpoint: ``(folder it ran in, its CompletedProcess)``. Tests leave its checkpoint and run folders as they
    are (copies for anything they change)."""
    import json

    from filelock import FileLock

    from _in_process import run_command

    root = tmp_path_factory.getbasetemp()
    # the session's folder, above each xdist worker's own (xdist's worker_id fixture is missing under -p no:xdist)
    root = root.parent if hasattr(request.config, "workerinput") else root
    cwd, saved = root / "trained_run", root / "trained_run.json"
    with FileLock(str(root / "trained_run.lock")):
        if not saved.is_file():
            cwd.mkdir(exist_ok=True)
            # the default agent (ppo_turn) trains on the batched engine: 8 envs x 8 decisions per rollout (one env
            # would step the batch 8 times as often), one rollout and one update, and clones the gap-acceptance
            # rule first (one episode): every part runs once; nothing here needs a policy that learnt anything
            fast = [o for o in FAST_PPO if not o.startswith(("agent.n_envs=", "agent.n_steps=", "agent.total_"))]
            # in this process (a fresh interpreter's imports cost ~9-12 CPU-s more than the run's own work); the
            # command as a process: every slow test that runs train (tests/test_cli.py, test_ppo_batched_shield.py)
            res = run_command("train", *fast, "agent.n_envs=8", "agent.n_steps=8", "agent.total_timesteps=64",
                              "agent.init_episodes=1", "agent.init_epochs=1", "train.eval_every=0", "run_name=tiny",
                              cwd=cwd)
            assert res.returncode == 0, res.stderr[-3000:]
            saved.write_text(json.dumps({"args": res.args, "stdout": res.stdout, "stderr": res.stderr}))
        out = json.loads(saved.read_text())
    return cwd, subprocess.CompletedProcess(out["args"], 0, out["stdout"], out["stderr"])


def zeros_action(_k, _obs):
    return np.zeros(1, dtype=np.float32)


# ----------------------------------------------------------------------------------------------- numba's cache
_WARMUP: dict = {}  # the numba warm-up under way in pytest's own process (-n): its parts' processes and logs


def pytest_configure(config):
    """Under ``pytest -n N`` with numba's cache empty (a fresh checkout: CI), fill it first in two processes
    (tests/_numba_warmup.py), so that the workers load the kernels instead of each compiling the same ones at
    once. Measured on 7 kernel-heavy test files, -n 2, an empty cache, load ~3: 329 s wall / 390 CPU-s without,
    137 s of warm-up + 138 s of tests / 350 CPU-s with. A filled cache (a checkout that ran them) skips it, as do
    the workers, ``--collect-only`` and ``--help`` (nothing runs a kernel there). Started here, waited for in
    :func:`pytest_collection`: the workers start and collect meanwhile."""
    workers = config.getoption("numprocesses", default=None)
    if hasattr(config, "workerinput") or workers in (None, 0, "0") or config.getoption("collectonly", False) \
            or config.getoption("help", False) or not _numba_cache_empty():
        return
    import tempfile
    import time

    print("numba's cache is empty: compiling the kernels once before the tests start (tests/_numba_warmup.py)",
          file=sys.stderr)
    script = Path(__file__).resolve().with_name("_numba_warmup.py")
    # one deadline for both parts (they run at once): a hung part may cost WARMUP_S, not WARMUP_S per part
    _WARMUP["deadline"] = time.monotonic() + WARMUP_S
    logs = {part: tempfile.TemporaryFile() for part in ("batch", "per_env")}  # a file: a pipe could fill and block
    _WARMUP["parts"] = {part: (subprocess.Popen([sys.executable, str(script), part], stdout=subprocess.DEVNULL,
                                                stderr=log), log) for part, log in logs.items()}


@pytest.hookimpl(tryfirst=True)
def pytest_collection(session):
    """The numba warm-up's end, waited for before any test runs. Here, not in :func:`pytest_configure`: under -n
    this process collects nothing, and xdist has started its workers (pytest_sessionstart), which import and
    collect the test files (~17 CPU-s each, no kernel compiled) while the warm-up compiles, on the cores that its
    shorter part leaves idle. Measured on a fresh clone (-n 2, empty cache): see the commit that made it."""
    _end_warmup(wait=True)


def pytest_unconfigure(config):
    """A session that ends before its collection (a usage error, ^C) leaves no warm-up running."""
    _end_warmup(wait=False)


@pytest.hookimpl(hookwrapper=True)
def pytest_cmdline_main(config):
    """An xdist worker whose session has ended (its results sent: xdist's ``workerfinished``, after which the
    controller ignores the channel's end) leaves at once, without the interpreter's teardown: that (numba's
    compiled libraries, torch, ~1,300 tests' objects) took ~3 s of wall after the last test, the controller waiting
    for both workers, with the cores otherwise idle (fresh-clone fast suite, -n 2). Only after a session that ended
    normally: a worker that failed earlier exits as usual, so xdist sees and reports it; and not under coverage.py,
    whose data a process writes as it exits."""
    outcome = yield
    output = getattr(config, "workeroutput", None)
    if output is not None and "exitstatus" in output and outcome.excinfo is None and "coverage" not in sys.modules:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(int(outcome.get_result() or 0))


def _end_warmup(wait: bool) -> None:
    """Wait for (``wait``) or stop the warm-up's parts; a part that failed or ran past the deadline is said."""
    import time

    for part, (proc, log) in _WARMUP.pop("parts", {}).items():  # a failed or slow warm-up only leaves the
        try:  # compiling to the workers
            rc = proc.wait(timeout=max(_WARMUP["deadline"] - time.monotonic(), 0.0) if wait else 0.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            rc = f"stopped after {WARMUP_S} s" if wait else "stopped: the session ended first"
        if rc != 0:  # said, not hidden: a warm-up that no longer runs would silently stop warming anything
            log.seek(0)
            last = (log.read().decode(errors="replace").strip().splitlines() or [""])[-1]
            print(f"numba warm-up {part!r} failed ({rc}){': ' + last[:200] if last else ''} (its kernels compile "
                  f"in the workers)", file=sys.stderr)
        log.close()


WARMUP_S = 600  # s, the most the warm-up may take (137 s measured on 2 cores at load ~3)
# Not lowered for tests: numba's LLVM level (NUMBA_OPT). Measured on a fresh clone (-n 2, empty cache, load ~3.3-4):
# the warm-up's parts took 97 / 115 CPU-s at the default 3 and 99 / 116 at 1, the whole command 774 / 785 CPU-s:
# LLVM is ~20 / 33 CPU-s of those parts (its lock's time), numba's own typing and lowering the rest. (Had it paid,
# its kernels would need their own cache folder: numba's cache index keys on signature, CPU and bytecode, not level.)


def _numba_cache_empty() -> bool:
    """No numba index file where the kernels' cache goes (NUMBA_CACHE_DIR, else beside av_gym's sources)."""
    from importlib.util import find_spec

    # found, not imported: this runs before the warm-up starts, and every CPU-second here delays it
    where = os.environ.get("NUMBA_CACHE_DIR") or str(Path(find_spec("av_gym").origin).resolve().parent)
    return not any(Path(where).rglob("*.nbi"))
