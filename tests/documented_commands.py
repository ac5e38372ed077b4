"""Every command README.md and docs/ invite a reader to type, and how the tests run each.

This is the one list: a fenced ``bash``/``sh``/``console`` block (or one with no language) in README.md or
docs/**/*.md is read line by line; each command line (``python``, ``python3``, ``tensorboard``, ``nice`` ...; a
``$ `` prompt is dropped, ``\\`` continuations joined, ``# comments`` removed, ``VAR=value`` lines expanded into the
block's later ``$VAR``) must appear in :data:`KNOWN` with how it is tested:

- ``"run"``: tests/test_documented_commands.py runs its tiny form (:func:`tiny`: the same command with the
  smallest budgets that still run every part, output in a temporary folder), as a subprocess, under ``-m slow``;
  the commands of one block run in order in one folder, so a later command reads what an earlier one wrote
  (``eval.sweep`` the multirun, ``train.export`` the run);
- ``"error"``: an example of a refused command line; the fast suite checks that the command prints exactly the
  ``error: ...`` line the document shows below it, with exit status 2;
- ``"ci"``: an install or test command that ``.ci/run`` itself runs (tests/test_ci.py checks they are the same);
- ``"covered:<test>"``: a test that already runs that command in a tiny form (the test must exist).

A new documented command without an entry fails ``test_every_documented_command_is_known``; an entry whose
command left the documents fails it too, so the list stays the documents' list.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROGRAMS = ("python", "python3", "tensorboard", "nice", "pip", "av-gym-train", "av-gym-eval")


@dataclass(frozen=True)
class Command:
    doc: str          # file it is documented in, relative to the repository
    line: int         # its first line there
    text: str         # normalised: one line, no prompt, no comment, variables expanded
    expected: tuple[str, ...] = ()  # for a ``$ `` prompt: the lines the document shows it printing


def documents() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def blocks(path: Path) -> list[list[Command]]:
    """The command lines of each fenced shell block of ``path``, in order."""
    rel = str(path.relative_to(ROOT))
    text = path.read_text()
    found = []
    for m in re.finditer(r"^```(\w*)[^\n]*\n(.*?)^```", text, re.S | re.M):
        lang, body = m.group(1), m.group(2)
        if lang not in ("", "bash", "sh", "shell", "console"):
            continue
        first = text[:m.start(2)].count("\n") + 1
        commands, env = [], {}
        lines = body.splitlines()
        i = 0
        while i < len(lines):
            start, line = i, lines[i]
            while line.rstrip().endswith("\\") and i + 1 < len(lines):
                i += 1
                line = line.rstrip()[:-1] + " " + lines[i].strip()
            i += 1
            prompt = line.lstrip().startswith("$ ")
            words = line.lstrip()[2:] if prompt else line.strip()
            try:
                argv = shlex.split(words, comments=True)
            except ValueError:
                continue
            if len(argv) == 1 and re.fullmatch(r"[A-Z_]+=\S+", argv[0]):
                key, value = argv[0].split("=", 1)
                env[key] = value
                continue
            if not argv or argv[0] not in PROGRAMS:
                continue
            # a word with a space keeps its quotes, so the tiny form splits as the shell would
            normal = " ".join(shlex.quote(a) if re.search(r"\s", a) else a for a in argv)
            for key, value in env.items():
                normal = normal.replace(f"${key}", value)
            expected = []
            while prompt and i < len(lines) and lines[i].strip() and not lines[i].lstrip().startswith("$ "):
                expected.append(lines[i].strip())
                i += 1
            commands.append(Command(rel, first + start, normal, tuple(expected)))
        if commands:
            found.append(commands)
    return found


def all_blocks() -> list[list[Command]]:
    return [b for path in documents() for b in blocks(path)]


# Every documented command (normalised as above) -> how it is tested. Kept in document order;
# ``python tests/documented_commands.py`` prints the documented commands not listed yet, ready to paste.
RESUME = "covered:tests/test_resume.py::test_kill_9_then_resume_reaches_the_same_total_without_tensorboard_duplicates"
KNOWN: dict[str, str] = {
    # README.md
    "python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && pip install -e . && python -m train":
        "covered:tests/test_cli.py::test_train_writes_checkpoint_config_tensorboard_and_prints_where",
    # the same with torch from PyTorch's CPU index (stock PyPI on a CPU-only machine): what follows the torch pin is
    # the command above, which that test runs; this machine's index serves the CPU build under the plain pin
    "python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 --index-url "
    "https://download.pytorch.org/whl/cpu && pip install -e . && python -m train":
        "covered:tests/test_cli.py::test_train_writes_checkpoint_config_tensorboard_and_prints_where",
    "python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && pip install -e .[test] && "
    "python -m pytest -q -n auto -m 'not slow'": "ci",
    "python -m pytest -q -n auto -m slow": "ci",
    # run from a folder of the user's own (tests/test_console_scripts.py: one holding conf/, agents/ ...)
    "av-gym-train --help": "run",
    "av-gym-eval env=left_turn agents=[always_proceed,ppo_turn] episodes=2": "run",
    "python -m eval.results_page --readme README.md":
        "covered:tests/test_results_page.py::test_check_fails_when_a_result_or_the_readme_changes",
    "tensorboard --logdir runs/": "run",
    "python -m train agent.total_timesteps=200000 seed=3": "run",
    "python -m train agent.vec_env=subproc agent.n_envs=2 agent.n_steps=256": "run",
    "python -m train env=lane_keeping agent=ppo agent.total_timesteps=3000 seed=4": "run",
    "python -m train env=lane_keeping agent=pid_paper": "run",
    "python -m eval env=left_turn agents=[always_proceed,ppo] episodes=100": "run",
    "python -m eval agents=[always_proceed,checkpoints/<run_name>]": "run",
    "python -m eval env=lane_keeping agents=[pid_paper] episodes=20": "run",
    "python -m eval env=lane_keeping env.track=B agents=[pid_paper] episodes=20": "run",
    "python -m eval env=left_turn env.mode=ccftap env.ccftap.ego_speed_kmh=20 env.ccftap.target_speed_kmh=60 "
    "env.ccftap.dt=0 agents=[always_proceed] episodes=1": "run",
    "python -m train env.mode=rush_hour": "error",
    "python -m train agent.epoch=3": "error",
    "python -m train -m env=lane_keeping agent=ppo sensors=gnss_imu seed=0,1,2 sensors.gnss.sigma=0.5,1.5,3": "run",
    "python -m eval -m env=lane_keeping agents=[pid_gnss] sensors=gnss_raw sensors.gnss.sigma=0.5,1.5,3 seed=1000000,1000100 "
    "episodes=3": "run",
    "python -m train -m agent=always_proceed shield=aeb shield.mode=perceived shield.detector.miss_rate=0,0.3,0.6,0.8 "
    "train.eval_seed=1000000,1100000,1200000 train.eval_episodes=20": "run",
    "python -m train -m hydra/launcher=slurm hydra.launcher.partition=cpu hydra.launcher.timeout_min=60 "
    "env=lane_keeping agent=ppo sensors=gnss_imu seed=0,1,2 sensors.gnss.sigma=0.5,1.5,3 "
    "run_name=ppo-s${seed}-g${sensors.gnss.sigma}": "run",
    "python -m eval.sweep runs/multirun/<stamp> --x shield.detector.miss_rate --metric collision": "run",
    "python -m eval env=lane_keeping agents=[pid_paper,pid_tuned,pilotnet] episodes=20": "run",
    "python -m eval env=lane_keeping env.track=B agents=[pid_paper,pid_tuned,pilotnet] episodes=20": "run",
    "python -m train agent=ppo_turn": "run",
    "python -m train agent=ppo_turn_shielded": "run",
    "python -m train agent=ppo_lane_localized env=lane_keeping": "run",
    "python -m train agent=ppo_lane_camera env=lane_keeping": "run",
    "python -m eval.curves runs/<run>/tb --out curves.png": "run",
    "python -m train.export checkpoints/<run> checkpoints/reference/<agent> --command 'python -m train ...' "
    "--overwrite-reference": "run",
    "python -m eval env=left_turn episodes=500 n_envs=2": "run",
    "python -m eval env=lane_keeping episodes=20": "run",
    "python -m eval.ccftap --agents [always_proceed,ppo_turn,ppo_turn_shielded] --variants [none,improved] "
    "--modes [ground_truth]": "run",
    "python -m eval env=left_turn agents=[always_proceed,always_proceed+aeb] episodes=200": "run",
    "python -m eval.ccftap --out docs/ccftap --overwrite": "run",
    "python -m eval.tracking --episodes 20": "run",
    "python -m eval.interventions --agents [always_proceed+aeb] --episodes 100": "run",
    "python -m eval env=lane_keeping agents=[pid_paper,pid_gnss,pid_localized] episodes=5": "run",
    "python -m eval.localization": "run",
    "python benchmarks/odometry.py": "run",
    "python -m train run_name=my-run agent.total_timesteps=200000": RESUME,
    "python -m train run_name=my-run agent.total_timesteps=200000 train.resume=true": RESUME,
    # docs/shield.md
    "python -m eval env=left_turn env.mode=ccftap agents=[always_proceed+aeb_paper] episodes=1": "run",
    "python -m eval.tracking --episodes 20 --out docs/tracking --overwrite": "run",
    # docs/sensors.md
    "python -m eval env=lane_keeping env.track=A agents=[checkpoints/reference/pilotnet] sensors=cameras "
    "episodes=20 n_envs=2": "run",
    "python -m eval env=lane_keeping env.track=A agents=[checkpoints/reference/pilotnet] sensors=cameras "
    "sensors.cameras.fog_visibility=80 episodes=20 n_envs=2": "run",
    "python -m eval env=lane_keeping env.track=A agents=[checkpoints/reference/pilotnet] sensors=cameras "
    "sensors.cameras.night=true episodes=20 n_envs=2": "run",
    "python -m eval env=lane_keeping env.track=A agents=[checkpoints/reference/pilotnet] sensors=cameras "
    "sensors.cameras.noise.pixel_std=8 sensors.cameras.noise.blur_sigma=0.8 sensors.cameras.noise.brightness=25 "
    "episodes=20 n_envs=2": "run",
    "python -m eval -m env=lane_keeping env.track=B agents=[checkpoints/reference/pilotnet] "
    "sensors=cameras sensors.cameras.noise.pixel_std=0,8,16,24,32 episodes=5 plots=false hydra.sweep.dir=<folder>":
        "run",
    "python -m eval.sweep <folder> --x sensors.cameras.noise.pixel_std --metric cte_mean_abs_units": "run",
    "python -m eval -m env=lane_keeping env.track=B agents=[checkpoints/reference/pilotnet] "
    "sensors=cameras sensors.cameras.fog_visibility=40,80,150,300,1000 sensors.cameras.night=false,true episodes=5 "
    "plots=false hydra.sweep.dir=<folder>": "run",
    "python -m eval.sweep <folder> --x sensors.cameras.fog_visibility --metric cte_mean_abs_units": "run",
    # docs/agents.md (PilotNet)
    "python -m train.pid_search": "run",
    "python -m train agent=pilotnet env=lane_keeping": "run",
    "python -m eval env=lane_keeping agents=[pid_paper,pid_tuned,pilotnet] episodes=20 videos=true": "run",
    "python -m eval env=lane_keeping env.track=B agents=[pid_paper,pid_tuned,pilotnet] episodes=20 videos=true": "run",
    "python benchmarks/pilotnet_inference.py": "run",
    # docs/shield.md (robustness to detector misses)
    "nice -n 10 python -m train -m agent=always_proceed shield=aeb shield.mode=perceived "
    "shield.detector.miss_rate=0.0,0.3,0.6,0.8 train.eval_seed=1000000,1100000,1200000 train.eval_episodes=20 "
    "train.progress_bar=false paths.checkpoints=/tmp/sweep_ckpt hydra.sweep.dir=runs/multirun/aeb_miss_rate": "run",
    "nice -n 10 python -m train -m agent=always_proceed shield=none,aeb train.eval_seed=1000000,1100000,1200000 "
    "train.eval_episodes=20 train.progress_bar=false paths.checkpoints=/tmp/sweep_ckpt "
    "hydra.sweep.dir=runs/multirun/aeb_reference": "run",
    "python -m eval.sweep runs/multirun/aeb_miss_rate --out docs/robustness/aeb_miss_rate "
    "--metrics collision,success,time_to_exit_s,min_ttc_s,intervention,override_fraction": "run",
    "python -m eval.sweep runs/multirun/aeb_reference "
    "--metrics collision,success,time_to_exit_s,min_ttc_s,intervention,override_fraction": "run",
    # docs/dagger.md
    "python -m train agent=dagger_turn": "run",
    "python benchmarks/oracle_labels.py --quick": "run",
    "python -m eval env=left_turn agents=[lookahead,belief_lookahead,dagger_turn,ppo_turn,dagger_turn_memory,"
    "checkpoints/reference/seeds/dagger_turn_memory/s1,checkpoints/reference/seeds/dagger_turn_memory/s3] split=test "
    "seed=2800000 episodes=1000 vec_env=batched n_envs=250": "run",
    "python -m eval.interventions --agents [dagger_turn+aeb] --episodes 1000 --split test --seed 2800000 "
    "--out runs/interventions_dagger": "run",
    "python -m eval.interventions --agents [dagger_turn_memory+aeb] --episodes 1000 --split test --seed 2800000 "
    "--out runs/interventions_memory": "run",
    "python -m train agent=dagger_turn_memory seed=2 agent.rounds=8 agent.round_episodes=192 agent.n_envs=64 "
    "train.eval_n=200 train.eval_episodes=0 train.progress_bar=false train.torch_threads=1 run_name=dagger_memory_s2":
        "run",
    "python -m train agent=dagger_turn_soft seed=2 agent.rounds=8 agent.round_episodes=192 agent.n_envs=64 "
    "train.eval_n=200 train.eval_episodes=0 train.progress_bar=false train.torch_threads=1 run_name=dagger_soft_s2":
        "run",
    "python -m train.operating_point checkpoints/<run_name> --thresholds [0.5,0.7,0.8,0.9,0.95,0.97,0.99] "
    "--episodes 300": "run",
    "python -m eval env=left_turn agents=[dagger_turn_soft,checkpoints/reference/seeds/dagger_turn_soft/s1,"
    "checkpoints/reference/seeds/dagger_turn_soft/s3] split=test seed=2800000 episodes=1000 vec_env=batched "
    "n_envs=250": "run",
    "python -m eval.interventions --agents [dagger_turn_memory+aeb_belief] --episodes 1000 --split test --seed 2800000 "
    "--out runs/interventions_memory_belief": "run",
    "python -m eval.interventions --agents [dagger_turn+aeb_belief] --episodes 1000 --split test --seed 2800000 "
    "--out runs/interventions_dagger_belief": "run",
    "python benchmarks/partition.py docs/results/left_turn_partition/results.csv --students dagger_turn "
    "dagger_turn_memory ppo_turn":
        "covered:tests/test_partition.py::test_the_partition_adds_up_to_the_oracles_edge",
    "python -m eval env=left_turn agents=[belief_tracks,dagger_turn_perceived,dagger_turn@turn_perceived,"
    "dagger_turn_perceived+aeb,dagger_turn@turn_perceived+aeb] split=test seed=2800000 episodes=1000 "
    "vec_env=batched n_envs=250": "run",
    "python benchmarks/partition.py docs/results/left_turn_partition/results.csv "
    "docs/results/left_turn_sensing_partition/results.csv --chain lookahead belief_lookahead belief_tracks "
    "dagger_turn_perceived": "covered:tests/test_partition_chain.py::test_the_chain_adds_up_to_the_first_agents_edge",
    "python -m train agent=dagger_turn_perceived": "run",
    "python -m train agent=dagger_turn_perceived seed=1 agent.rounds=6 agent.round_episodes=128 train.eval_n=100 "
    "train.eval_episodes=0 train.torch_threads=1 run_name=dagger_perceived_s1": "run",
    "python benchmarks/oracle_labels.py --perceived 64 --batch 32": "run",
    "python docs/make_dagger_figure.py docs/dagger/rounds_perceived.csv --sensors turn_perceived "
    "--out docs/dagger_perceived.png": "run",
    "python -m train.operating_point checkpoints/reference/dagger_turn_perceived --thresholds [0.7,0.8] --episodes 100": "run",
    "python -m train.operating_point checkpoints/<run_name> --thresholds [0.5,0.7,0.8,0.9,0.95] --episodes 300": "run",
    "python docs/make_dagger_figure.py docs/dagger/rounds.csv --sensors 'turn_truth; memory_s*: turn_truth_memory' "
    "--out docs/dagger.png": "run",
    "python -m train agent=dagger_turn_memory seed=1 agent.rounds=8 agent.round_episodes=128 agent.round_growth=1.5 "
    "agent.n_envs=64 train.eval_n=300 train.eval_episodes=0 train.progress_bar=false train.torch_threads=1 "
    "run_name=dagger_curve_s1": "run",
    "python -m eval env=left_turn agents=[belief_lookahead] split=validation episodes=500 vec_env=batched n_envs=250 "
    "out_dir=runs/dagger_curve_planner_val": "run",
    "python docs/make_dagger_figure.py --curve docs/dagger/learning_curve.csv --highlight dagger_curve_* "
    "--out docs/dagger_learning_curve.png": "run",
    "python -m train agent=ppo_turn agent.init=null agent.init_from=checkpoints/reference/dagger_turn seed=1 "
    "agent.total_timesteps=30720 train.eval_every=3072 train.eval_n=300 train.eval_episodes=0 run_name=dagger_ppo_s1":
        "run",
}

# A command that reads what another documented command writes, documented in a block of its own: the tiny form
# of the producer runs first (the eval.sweep example reads the shield sweep of the block above it).
PRODUCERS: dict[str, str] = {
    "python -m eval.sweep runs/multirun/<stamp> --x shield.detector.miss_rate --metric collision":
        "python -m train -m agent=always_proceed shield=aeb shield.mode=perceived "
        "shield.detector.miss_rate=0,0.3,0.6,0.8 train.eval_seed=1000000,1100000,1200000 train.eval_episodes=20",
}

# Placeholders a document writes for the reader's own value -> what the tiny form uses.
PLACEHOLDERS = {"checkpoints/<run_name>": "checkpoints/reference/ppo_turn"}


def kind(command: Command) -> str | None:
    return KNOWN.get(command.text)


# ------------------------------------------------------------------------------------------------ tiny forms
FAST_TRAIN = ["train.progress_bar=false", "train.eval_episodes=1", "train.eval_every=0", "train.eval_n=0",
              "train.video_every=0", "train.checkpoint_every=64"]
PPO_BATCHED = ["agent.total_timesteps=64", "agent.n_envs=8", "agent.n_steps=8", "agent.batch_size=64",
               "agent.n_epochs=1", "agent.init_episodes=2", "agent.init_epochs=1"]
PPO_PER_ENV = ["agent.total_timesteps=64", "agent.n_steps=32", "agent.batch_size=32", "agent.n_epochs=1",
               "agent.init_episodes=2", "agent.init_epochs=1"]
PILOTNET = ["agent.demo_laps=1", "agent.demo_max_steps=30", "agent.epochs=1"]
DAGGER = ["agent.rounds=2", "agent.round_episodes=2", "agent.n_envs=2", "agent.fit_epochs=1", "agent.extractor=mlp"]
# agents whose config trains per-env (a tracker, a shield, an image): their tiny form keeps n_envs at 1
PER_ENV_AGENTS = ("ppo", "ppo_turn_shielded", "ppo_turn_perceived", "ppo_lane_localized", "ppo_lane_camera")


def _set(argv: list[str], key: str, value: str) -> list[str]:
    """``key=value`` in place of any ``key=...`` of ``argv`` (Hydra refuses a key given twice)."""
    kept = [a for a in argv if not a.startswith(f"{key}=")]
    return [*kept, f"{key}={value}"]


def _first_two(argv: list[str]) -> list[str]:
    """A ``-m`` sweep's comma lists cut to their first two values (still a sweep, a fraction of the jobs)."""
    out = []
    for a in argv:
        key, eq, value = a.partition("=")
        if eq and "," in value and not value.startswith(("[", "'[", '"[')) and not key.startswith(("agents", "'agents")):
            value = ",".join(value.split(",")[:2])
        out.append(f"{key}{eq}{value}")
    return out


@dataclass
class Chain:
    """What earlier commands of a block left for later ones, in the block's temporary folder."""

    tmp: Path
    multirun: Path | None = None
    run: str | None = None
    runs: int = 0
    evals: int = 0  # each eval writes its own folder (eval refuses to write over an evaluation)
    named: dict | None = None  # a documented hydra.sweep.dir (``<folder>``, runs/multirun/x) -> where it went


def tiny(command: Command, chain: Chain) -> list[str]:
    """The command's argv with the smallest budgets that still run each part, writing under ``chain.tmp``."""
    text = command.text
    for placeholder, value in PLACEHOLDERS.items():
        text = text.replace(placeholder, value)
    argv = shlex.split(text)
    while argv and argv[0] == "nice":  # nice -n 10 python ...
        argv = argv[3:] if argv[1] == "-n" else argv[1:]
    tmp = chain.tmp
    if argv[0] == "tensorboard":
        return ["tensorboard", "--inspect", "--logdir", str(tmp)]
    if argv[0] in CONSOLE_SCRIPTS:  # python -m train / eval from any folder: the same tiny forms
        if "--help" in argv:
            return argv
        module = CONSOLE_SCRIPTS[argv[0]]
        return [argv[0], *(_tiny_train(argv[1:], chain) if module == "train" else _tiny_eval(argv[1:], chain))]
    assert argv[0] in ("python", "python3"), command
    if argv[1] != "-m":  # a script: benchmarks/*.py, docs/*.py
        return ["python", *argv[1:], *(script_argv(argv[1], tmp) if argv[1] in SCRIPT_ARGS else [])]
    module, args = argv[2], argv[3:]
    if module == "train":
        return ["python", "-m", "train", *_tiny_train(args, chain)]
    if module == "eval":
        return ["python", "-m", "eval", *_tiny_eval(args, chain)]
    return ["python", "-m", module, *_tiny_tool(module, args, chain)]


def _sweep_dir(args: list[str], chain: Chain) -> list[str]:
    chain.multirun = chain.tmp / f"multirun{chain.runs}"
    chain.runs += 1
    documented = next((a.split("=", 1)[1] for a in args if a.startswith("hydra.sweep.dir=")), None)
    if documented:
        chain.named = {**(chain.named or {}), documented: chain.multirun}
    return _set(_first_two(args), "hydra.sweep.dir", str(chain.multirun))


def _tiny_train(args: list[str], chain: Chain) -> list[str]:
    sweep = "-m" in args
    if sweep and any(a.startswith("hydra.launcher.partition=") for a in args):  # the SLURM example, run locally
        args = ["hydra/launcher=submitit_local" if a == "hydra/launcher=slurm" else a for a in args
                if not a.startswith("hydra.launcher.partition=")]
    agent = next((a.split("=", 1)[1] for a in args if a.startswith("agent=")), "ppo_turn")
    for option in FAST_TRAIN:
        args = _set(args, *option.split("=", 1))
    if agent.startswith("ppo") or agent == "ppo":
        per_env = agent in PER_ENV_AGENTS or any(a == "agent.vec_env=subproc" for a in args)
        for option in PPO_PER_ENV if per_env else PPO_BATCHED:
            args = _set(args, *option.split("=", 1))
        if per_env and not any(a.startswith("agent.n_envs=") for a in args):
            args = _set(args, "agent.n_envs", "1")
    elif agent.startswith("dagger"):
        for option in DAGGER:
            if agent == "dagger_turn_perceived" and option.startswith("agent.extractor="):
                continue  # it starts from dagger_turn's network (init_from): the extractor must stay that one
            args = _set(args, *option.split("=", 1))
    elif agent == "pilotnet":
        for option in PILOTNET:
            args = _set(args, *option.split("=", 1))
    args = _set(args, "paths.runs", str(chain.tmp / "runs"))
    args = _set(args, "paths.checkpoints", str(chain.tmp / "checkpoints"))
    if sweep:
        args = _set(_sweep_dir(args, chain), "hydra.launcher.n_jobs", "1") if not any(
            a.startswith("hydra/launcher=submitit") for a in args) else _sweep_dir(args, chain)
    elif not any(a.startswith("run_name=") for a in args):
        chain.run = f"run{chain.runs}"
        chain.runs += 1
        args = _set(args, "run_name", chain.run)
    else:
        chain.run = next(a.split("=", 1)[1] for a in args if a.startswith("run_name="))
    return args


def _tiny_eval(args: list[str], chain: Chain) -> list[str]:
    n_envs = next((a.split("=", 1)[1] for a in args if a.startswith("n_envs=")), "1")
    args = _set(args, "episodes", n_envs if n_envs.isdigit() and int(n_envs) <= 2 else "2")
    args = _set(args, "progress_bar", "false")
    # a bare kind (`ppo`) is your newest run of it: the block's own runs, never what this checkout happens to hold
    args = _set(args, "paths.checkpoints", str(chain.tmp / "checkpoints"))
    if "-m" in args:
        return _set(_sweep_dir(args, chain), "hydra.launcher.n_jobs", "1")
    chain.evals += 1
    return _set(args, "out_dir", str(chain.tmp / f"eval{chain.evals}"))


def _flag(args: list[str], flag: str, *values: str) -> list[str]:
    """``flag values`` in place of any ``flag ...`` (argparse keeps the last one, but the tiny form reads better)."""
    out, skip = [], 0
    for a in args:
        if skip:
            skip -= 1
            continue
        if a == flag:
            skip = 1 if values else 0  # a switch (--overwrite) has no value to drop with it
            continue
        out.append(a)
    return [*out, flag, *values]


def _tiny_tool(module: str, args: list[str], chain: Chain) -> list[str]:
    tmp = chain.tmp
    if module == "eval.sweep":
        folder = str((chain.named or {}).get(args[0]) or chain.multirun or args[0])
        return _flag([folder, *args[1:]], "--out", str(tmp / "sweep"))
    if module == "eval.curves":
        tb = str(tmp / "runs" / (chain.run or "run0") / "tb")
        return _flag([tb, *args[1:]], "--out", str(tmp / "curves.png"))
    if module == "train.export":
        run = str(tmp / "checkpoints" / (chain.run or "run0"))
        return [run, str(tmp / "export"), *args[2:]]
    for flag, values in TOOL_ARGS.get(module, []):
        args = _flag(args, flag, *values)
    if module in OUT_FLAG:
        args = _flag(args, OUT_FLAG[module], str(tmp / module))
    return args


CONSOLE_SCRIPTS = {"av-gym-train": "train", "av-gym-eval": "eval"}  # pyproject [project.scripts]
OUT_FLAG = {"eval.ccftap": "--out", "eval.tracking": "--out", "eval.interventions": "--out",
            "eval.localization": "--out-dir", "eval.tradeoff": "--out", "train.pid_search": "--out"}
TOOL_ARGS = {
    "eval.ccftap": [("--ego", ["20"]), ("--target", ["60"]), ("--dts", ["0"]), ("--workers", ["1"]),
                    ("--overwrite", [])],  # a block's commands share one --out
    "eval.tracking": [("--episodes", ["1"]), ("--miss-rates", ["0.3"]), ("--overwrite", [])],
    "eval.interventions": [("--episodes", ["1"]), ("--overwrite", [])],  # a block's commands share one --out
    "eval.localization": [("--lap-seeds", ["100"]), ("--turn-seeds", ["100"]), ("--pid-seeds", ["100"])],
    "eval.tradeoff": [("--episodes", ["4"]), ("--n-envs", ["4"])],
    "train.pid_search": [("--grid", ["quick"]), ("--refine", ["0"]), ("--seeds", ["0"])],
    "train.operating_point": [("--episodes", ["2"]), ("--thresholds", ["[0.5,0.9]"])],
}
# Every script a document tells a reader to run (``python benchmarks/<name>.py``, ``python docs/<name>.py``: in a fenced
# block, an indented one or inline prose) -> the arguments of its tiny form; ``{tmp}`` is the test's folder. A
# command of a fenced block runs as written with these appended (argparse keeps the last of a flag); a script named
# only outside fenced blocks runs with these alone (tests/test_documented_commands.py: test_documented_scripts_run).
PARTITION_CSV = "docs/results/left_turn_partition/results.csv"
SCRIPT_ARGS = {
    "benchmarks/aeb_cost.py": ["--vehicles", "2", "--n", "2", "--repeat", "1"],
    "benchmarks/batched_distribution.py": [PARTITION_CSV, PARTITION_CSV],  # the documented pair: two evals' csv
    "benchmarks/batched_perception.py": ["--agent", "gap_acceptance@turn_perceived", "--B", "2",
                                         "--batch-episodes", "2", "--per-env-episodes", "1"],
    "benchmarks/batched_speed.py": ["--sizes", "1,2", "--seconds", "0.1", "--out", "{tmp}/batched_speed.png"],
    "benchmarks/belief_information.py": ["--episodes", "2", "--steps", "2", "--samples", "2"],
    "benchmarks/belief_planner.py": ["--episodes", "2", "--samples", "2", "--thresholds", "0.1", "--n-envs", "2"],
    "benchmarks/label_noise.py": ["checkpoints/reference/dagger_turn_memory", "--model", "model.zip", "--episodes",
                                  "1", "--n-envs", "1", "--samples", "2", "4", "--out", "{tmp}/noise.csv"],
    "benchmarks/odometry.py": ["--scans", "20", "--repeats", "1"],
    "benchmarks/oracle_labels.py": ["--quick"],
    "benchmarks/belief_tracks_sweep.py": ["--episodes", "1", "--n-envs", "1"],
    "benchmarks/belief_tracks_ablate.py": ["--episodes", "1", "--seed", "1000000", "--truth=all,crash,-users",
                                           "--out", "{tmp}/ablate.json", "--set", "samples=2"],
    "benchmarks/belief_tracks_diagnose.py": ["--seeds", "1000000", "--set", "samples=2"],
    "benchmarks/belief_tracks_pairs.py": ["--seeds", "1000000", "--set", "samples=2"],
    "benchmarks/belief_tracks_takeback.py": ["--seeds", "1000000", "--set", "samples=2"],
    "benchmarks/belief_tracks_waiting.py": ["--seeds", "1000000", "--set", "samples=2"],
    "benchmarks/belief_tracks_confirm.py": ["--seeds", "1000000", "--set", "samples=2"],
    "benchmarks/belief_tracks_state.py": ["--seeds", "1000000", "--set", "samples=2"],
    "benchmarks/belief_tracks_motion.py": ["--episodes", "1", "--fit", "0.5", "--set", "samples=2"],
    "benchmarks/partition.py": [PARTITION_CSV, "--resamples", "10"],
    "benchmarks/pilotnet_inference.py": ["--frames", "20"],
    "benchmarks/sensor_cost.py": ["--steps", "5", "--repeats", "1"],
    "benchmarks/sensor_kernels.py": ["--steps", "5", "--repeats", "1"],
    "benchmarks/sim_speed.py": ["--quick"],
    "benchmarks/soak.py": ["--episodes", "2", "--sample-every", "1", "--quiet", "--out", "{tmp}/soak.md"],
    "docs/make_camera_frames.py": ["--out", "{tmp}/cameras"],
    "docs/make_dagger_figure.py": ["--out", "{tmp}/dagger.png"],
    "docs/make_lidar_figure.py": ["--out", "{tmp}/lidar"],
}
SCRIPT = re.compile(r"(?<![\w/.-])python3? ((?:benchmarks|docs)/[\w/]+\.py)")


def documented_scripts() -> dict[str, list[str]]:
    """Every script README.md or docs/**/*.md tells a reader to run -> where (``docs/<page>.md:12``), wherever the page
    writes the command: a fenced block, an indented block or a sentence."""
    found: dict[str, list[str]] = {}
    for path in documents():
        text = path.read_text()
        for m in SCRIPT.finditer(text):
            found.setdefault(m.group(1), []).append(f"{path.relative_to(ROOT)}:{text[:m.start()].count(chr(10)) + 1}")
    return found


def script_argv(script: str, tmp: Path) -> list[str]:
    """The tiny form's arguments of a documented script, writing under ``tmp``."""
    return [a.replace("{tmp}", str(tmp)) for a in SCRIPT_ARGS[script]]


if __name__ == "__main__":
    for block in all_blocks():
        for c in block:
            if c.text not in KNOWN:
                print(f"    {c.text!r}: \"run\",  # {c.doc}:{c.line}")
