"""The settings of ``python -m train`` and ``python -m eval`` besides their sections (``env``, ``sensors``,
``agent``, ``shield``, each checked by its own kind's Params): typed, with defaults and reasons here, stored in
Hydra's ConfigStore as ``command/train`` and ``command/eval`` (conf/__init__.py) so that train.yaml and eval.yaml
hold only the defaults list, interpolations and Hydra's own settings."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from av_gym.params import EPISODES_MAX, SEED_MAX, Params, param

# Worker processes (each a full env stack, ~180 MB): 64 already oversubscribes any workstation's cores.
PROCESSES_MAX = 64


@dataclass(frozen=True)
class Command(Params):
    """A command's own settings, typed: built once where the command starts (:meth:`of`) and passed down, so that
    nothing below reads the composed config's settings raw."""

    @classmethod
    def of(cls, cfg: Mapping | Any):
        """This command's settings in a composed config (an OmegaConf node or a plain mapping; the sections
        ``env``, ``agent`` ... aside; a missing setting takes its default). The config's problems are said by
        :func:`conf.check.validate_config`, with the command line's paths; here a bad value raises ParamError."""
        if hasattr(cfg, "_metadata"):
            from omegaconf import OmegaConf

            cfg = OmegaConf.to_container(cfg, resolve=True)
        return cls.from_mapping({k: v for k, v in cfg.items() if k in cls.field_names()})


@dataclass(frozen=True)
class TrainOptions(Params):
    """``train.*``: checkpoints, the evaluations during and after training, progress."""

    checkpoint_every: int = param(8000, "env steps", ge=1, doc="between atomic checkpoints (latest.zip, RNG states "
                                                                "inside), at rollout boundaries: PPO's decisions x "
                                                                "agent.action_repeat (eval_every counts decisions)")
    resume: bool = param(False, doc="continue an interrupted run from checkpoints/<run_name>/latest.zip (PPO: to "
                                    "the same total steps; DAgger: from the next round); the run's config.yaml "
                                    "must match this one, and a finished run (its model.zip) is refused")
    overwrite: bool = param(False, doc="a run_name whose checkpoints/ or runs/ folder exists is refused unless "
                                       "resuming; true deletes that run's folders first and starts afresh")
    eval_episodes: int = param(100, "episodes", ge=0, le=EPISODES_MAX, doc="brief evaluation after training, seeds eval_seed.. "
                                                          "(100: a rate's 95 % interval is about ±0.1, enough to tell "
                                                          "a policy from always-proceed's 0.5 / 0.5)")
    eval_n_envs: int = param(2, "processes", ge=1, le=PROCESSES_MAX, doc="worker processes for the brief evaluation (1 = in this "
                                                       "process; the same rows)")
    eval_seed: int | None = param(None, ge=0, le=SEED_MAX, doc="first seed of the evaluations during and after training, in the "
                                                   "validation split (av_gym/seeds.py; null = its start): they pick "
                                                   "best.zip, so they must never be test seeds")
    eval_every: int = param(10000, "policy steps", ge=0, doc="between evaluations on fixed seeds during training, "
                                                              "counted as agent.total_timesteps is (x action_repeat "
                                                              "env steps; 0 = none)")
    eval_n: int = param(30, "episodes", ge=0, le=EPISODES_MAX, doc="per evaluation during training (seeds eval_seed..; best.zip kept; "
                                                  "on the batched engine with agent.vec_env=batched)")
    video_every: int = param(50000, "policy steps", ge=0, doc="between rendered evaluation episodes (GIF + "
                                                               "TensorBoard; 0 = none)")
    baseline: str = param("auto", doc="agent compared against in the brief evaluation (auto: always_proceed and "
                                      "gap_acceptance on the left turn, pid_paper on lane keeping)")
    progress_bar: bool = param(True)
    torch_threads: int = param(1, ge=1, doc="torch intra-op threads (one per process: the envs use the other core)")


@dataclass(frozen=True)
class TrainPaths(Params):
    runs: str = param("runs", doc="logs and TensorBoard: runs/<run_name>/")
    checkpoints: str = param("checkpoints", doc="checkpoints/<run_name>/{model.zip,latest.zip,config.yaml}")


@dataclass(frozen=True)
class TrainCommand(Command):
    """``python -m train``'s own settings."""

    seed: int = param(0, ge=0, le=SEED_MAX, doc="seeds the env stream, the policy's initialisation and PPO's sampling")
    run_name: str = param("run", name_like=True, doc="folder name under paths.runs and paths.checkpoints (train.yaml: "
                                                     "env-agent-seed-time)")
    paths: TrainPaths = param(TrainPaths())
    train: TrainOptions = param(TrainOptions())


@dataclass(frozen=True)
class EvalPaths(Params):
    checkpoints: str = param("checkpoints", doc="where trained kinds (ppo, ppo_turn ...) find their newest checkpoint")


@dataclass(frozen=True)
class EvalCommand(Command):
    """``python -m eval``'s own settings."""

    agents: tuple[str, ...] = param((), min_items=1, doc="names from conf/agent/ (rule-based, or trained: the newest checkpoint "
                                            "of that config), a trained kind, or a checkpoint path; eval.yaml: the "
                                            "env's compare list")
    episodes: int = param(20, ge=1, doc="episodes per agent (bounded by the split's seed range, av_gym/seeds.py)")
    split: Literal["train", "validation", "test"] = param(
        "validation", doc="which seed range the episodes come from (av_gym/seeds.py): validation for looking and "
                          "deciding, test only for reported tables (docs/results.md), train is what learning saw")
    seed: int | None = param(None, ge=0, le=SEED_MAX, doc="episode i uses seed + i, the same seeds for every agent; null = the "
                                             "split's first seed; a seed range outside the split is refused")
    n_envs: int = param(1, ge=1, le=1024, doc="worker processes sharing the episodes (1 = in this process); the "
                                              "metrics are bit-identical whatever n_envs, as every episode is "
                                              "seeded on its own. <= 64 processes (subproc), <= 1024 episodes "
                                              "stepped together (batched)")
    vec_env: Literal["subproc", "batched"] = param("subproc", doc="subproc: per-env stacks (n_envs worker processes); "
                                                                  "batched: the left turn's batched engine, n_envs "
                                                                  "episodes stepped together (eval/batched.py)")
    workers: int = param(1, "processes", ge=1, le=PROCESSES_MAX, doc="vec_env=batched: processes sharing the "
                                                                      "episodes, each a batch of n_envs on its own "
                                                                      "contiguous part of the seeds (1 = this "
                                                                      "process); the same rows whatever workers")
    paths: EvalPaths = param(EvalPaths())
    out_dir: str = param("runs/eval", doc="results.csv and results.md (eval.yaml: Hydra's run folder)")
    progress_bar: bool = param(True)
    plots: bool = param(True, doc="lane keeping: CTE along the lap (PNG) per agent, on the first seed")
    videos: bool = param(False, doc="lane keeping: one lap per agent from the centre camera (lap_<agent>.webm); "
                                    "left turn: each agent's first episode top-down (turn_<agent>.webm, VP8)")
    overwrite: bool = param(False, doc="an out_dir that already holds results.csv or results.md is refused (a "
                                       "finished evaluation is not replaced by accident); true replaces them")

    def relations(self) -> list[str]:
        if self.vec_env == "subproc" and self.n_envs > PROCESSES_MAX:
            return [f"@n_envs must be at most {PROCESSES_MAX} with @vec_env=subproc (a process each), got "
                    f"{self.n_envs}; vec_env=batched takes up to 1024"]
        if self.vec_env == "subproc" and self.workers > 1:
            return [f"@workers={self.workers} runs only with @vec_env=batched (its batches in that many processes); "
                    f"with vec_env=subproc, @n_envs is the number of processes"]
        return []


COMMANDS: dict[str, type[Command]] = {"train": TrainCommand, "eval": EvalCommand}
SECTIONS = {"train": ("env", "sensors", "agent", "shield"), "eval": ("env", "sensors", "shield")}


def help_groups(command: str) -> str:
    """The config groups ``command`` lets a user choose (:data:`SECTIONS`), one line each with its options (the
    yaml files of ``conf/<group>/``), for ``--help`` (conf/hydra/help/av_gym.yaml). Hydra's own listing would also
    show the groups conf/__init__.py stores from the Params (``aeb``, ``agent_kind``, ``command``, ``scenario``,
    ``sensor``): they fill the chosen groups' defaults and are refused on the command line."""
    from importlib import resources

    root = resources.files("conf")
    lines = []
    for group in sorted(SECTIONS[command]):
        options = sorted(f.name.removesuffix(".yaml") for f in root.joinpath(group).iterdir()
                         if f.name.endswith(".yaml"))
        lines.append(f"{group}: {', '.join(options)}")
    return "\n".join(lines)
