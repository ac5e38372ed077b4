"""``python -m train [env=left_turn] [agent=ppo] [seed=0] [agent.total_timesteps=...]``

Builds the env stack and the agent from ``conf/``, trains (PPO with stable-baselines3; rule-based agents have
nothing to train), logs to TensorBoard, writes checkpoints atomically under ``checkpoints/<run_name>/`` with the
resolved config beside them, then evaluates the result briefly against the scenario's baseline."""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from av_gym.errors import ConfigError, check_folder, folder_problem, run_cli, run_hydra

# What the brief evaluation after training compares the trained agent with (train.baseline: auto): on the left turn
# the do-nothing-clever driver and the two-parameter rule a learned driver must beat.
BASELINES = {"left_turn": ("always_proceed", "gap_acceptance"), "lane_keeping": ("pid_paper",)}


def _kind(cfg: DictConfig):
    """The agent's kind (agents/registry.py AGENT_KINDS): its Params, and for a trained kind its trainer."""
    from agents.registry import AGENT_KINDS

    return AGENT_KINDS.get(cfg.agent.get("kind"))


def validation_seeds(cfg: DictConfig, n: int) -> range:
    """``n`` seeds of the validation split from ``train.eval_seed`` (default: the split's start): the evaluations
    during training pick ``best.zip`` and the one after it is looked at, so they may never be test seeds."""
    from av_gym.seeds import config_seeds

    return config_seeds("validation", n, cfg.train.get("eval_seed"), "train.eval_seed")


def _validate(cfg: DictConfig) -> None:
    """Every field against the schema (the agent section: its kind's Params), then what its trainer needs."""
    from agents.registry import resolve
    from conf.check import validate_config

    validate_config(cfg, "train")
    validation_seeds(cfg, max(int(cfg.train.eval_episodes), int(cfg.train.eval_n)))
    agent = cfg.agent
    if cfg.env.name not in agent.scenarios:
        raise ConfigError(f"agent {agent.name!r} drives scenarios {list(agent.scenarios)}, not env={cfg.env.name}")
    kind = _kind(cfg)
    if kind.train_checks:
        problems = resolve(kind.train_checks)(cfg)
        if problems:
            raise ConfigError(problems[0])


def train(cfg: DictConfig) -> dict:
    """Train and briefly evaluate; returns where things went (``run_dir``, ``tensorboard``, ``checkpoint``)."""
    import torch

    from av_gym.make import make_env
    from eval.agents import plan_agent, resolve_agent
    from eval.report import write_results
    from eval.runner import EpisodeJob, run_episodes, run_episodes_parallel
    from train.checkpoint import write_text_atomic
    from train.run_folder import clear_for_overwrite, release_all

    _validate(cfg)
    make_env(cfg.env, cfg.sensors, cfg.shield).close()  # fail fast on a bad env/sensors/shield config
    torch.set_num_threads(int(cfg.train.torch_threads))
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    ckpt_dir = Path(cfg.paths.checkpoints) / cfg.run_name
    if HydraConfig.get().mode == RunMode.MULTIRUN:  # jobs of a sweep started in the same second share run_name
        ckpt_dir = ckpt_dir.with_name(f"{ckpt_dir.name}-j{HydraConfig.get().job.num}")
    tb_dir = run_dir / "tb"
    check_folder(ckpt_dir, "paths.checkpoints")  # one line, not a traceback, if it cannot be
    claim_run(cfg, ckpt_dir, None)  # ours alone (a lock), resumable, or refused: before config.yaml is written
    release_all(keep=ckpt_dir)
    if bool(cfg.train.overwrite) and not bool(cfg.train.resume):
        removed = clear_for_overwrite(ckpt_dir, run_dir)
        if removed:
            print(f"[train] train.overwrite=true: removed the previous run's {len(removed)} files and folders")
    write_text_atomic(ckpt_dir / "config.yaml", OmegaConf.to_yaml(cfg, resolve=True))

    agent, env_name = cfg.agent, cfg.env.name
    model_path = None
    if _kind(cfg).trained():
        from agents.registry import resolve
        from train.run_folder import discard_if_unstarted

        try:
            model_path = resolve(_kind(cfg).trainer)(cfg, ckpt_dir, run_dir)
        except ConfigError:
            # refused by the trainer before it wrote anything (an agent.init_from that does not fit): the fresh
            # run's config.yaml goes too, or the run_name would be refused as taken
            if not bool(cfg.train.resume):
                discard_if_unstarted(ckpt_dir)
            raise
    else:
        print(f"[train] agent {agent.name!r} is rule-based: nothing to train")

    rows = []
    n = int(cfg.train.eval_episodes)
    if n > 0:
        seeds = validation_seeds(cfg, n)
        baselines = list(BASELINES[env_name]) if cfg.train.baseline == "auto" else [cfg.train.baseline]
        specs = [str(ckpt_dir), *baselines] if model_path else [agent.name]
        sensors, shield = (OmegaConf.to_container(c, resolve=True) for c in (cfg.sensors, cfg.shield))
        env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
        # A worker process costs a few seconds to start (imports, env, policy): worth it from ~10 episodes each.
        n_envs, progress = min(int(cfg.train.eval_n_envs), n // 10), bool(cfg.train.progress_bar)
        ran_with = {}  # label → the sensors it ran with, stated in results.md
        batched = agent.get("vec_env") == "batched"  # trained on the batch: evaluated there too, all at once
        title = f"{cfg.run_name}: brief evaluation, {n} episodes of the validation split (seeds {seeds.start}.." \
                f"{seeds.stop - 1})"
        try:  # rows are appended episode by episode: Ctrl-C/SIGTERM keeps (and writes) every finished one
            for spec in specs:
                plan = plan_agent(spec, env_name, sensors, shield, cfg.paths.checkpoints)
                label = agent.name if spec == str(ckpt_dir) else plan.label
                ran_with[label] = plan.sensors
                if batched:
                    from eval.batched import run_episodes_batched

                    env = make_env(env_cfg, plan.sensors, plan.shield)
                    _, policy = resolve_agent(plan.spec, env, env_name, cfg.paths.checkpoints)
                    env.close()
                    run_episodes_batched(env_cfg, plan, policy, seeds, min(n, 256), label, progress=progress,
                                         out=rows)
                    continue
                if n_envs > 1:  # each episode depends on its seed only: the same rows as in-process, sooner
                    job = EpisodeJob(env_cfg, plan.sensors, plan.shield, plan.spec, env_name,
                                     str(cfg.paths.checkpoints), label)
                    run_episodes_parallel(job, seeds, n_envs, progress=progress, out=rows)
                    continue
                env = make_env(env_cfg, plan.sensors, plan.shield)
                _, policy = resolve_agent(plan.spec, env, env_name, cfg.paths.checkpoints)
                run_episodes(env, policy, seeds, label, progress=progress, out=rows)
                env.close()
        except KeyboardInterrupt:
            if rows:
                write_results(rows, run_dir, env_name, f"{title} (interrupted after {len(rows)} episodes)",
                              sensors=ran_with, split="validation")
            print(f"[train] interrupted during the brief evaluation: {len(rows)} episodes measured"
                  + (f", in {run_dir}/results.csv" if rows else ""), file=sys.stderr)
            raise
        table = write_results(rows, run_dir, env_name, title, sensors=ran_with, split="validation")
        print(f"\n[train] brief evaluation on {n} validation seeds ({seeds.start}..{seeds.stop - 1}):\n\n{table}\n")

    where = {"run_dir": str(run_dir), "tensorboard": str(tb_dir),
             "checkpoint": str(model_path) if model_path else None, "config": str(ckpt_dir / "config.yaml")}
    print(f"[train] logs:        {run_dir}")
    if model_path:
        print(f"[train] tensorboard: tensorboard --logdir {tb_dir}")
        print(f"[train] checkpoint:  {model_path.resolve()}  (config beside it: config.yaml)")
    return where


def claim_run(cfg: DictConfig, ckpt_dir: Path, runs_dir: Path | None) -> None:
    """The run's folders for this process alone (train/run_folder.py): refused if they hold another run (unless
    resuming or overwriting), if a resume does not match the run's config.yaml, or if another process trains it."""
    from train.run_folder import claim

    claim(ckpt_dir, runs_dir, bool(cfg.train.resume), bool(cfg.train.overwrite),
          {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("env", "sensors", "shield", "agent")})


def _check_command_line() -> None:
    from conf.check import check_command_line

    configs = check_command_line("train", sys.argv[1:])
    for cfg in configs:
        _validate(cfg)
        # where the checkpoints go, before Hydra makes the run folder (a sweep's -j<n> suffix fits: run_name is
        # bounded in the schema)
        problem = folder_problem(Path(cfg.paths.checkpoints) / str(cfg.run_name), "paths.checkpoints")
        if problem:
            raise ConfigError(problem)
    if len(configs) == 1 and not any(a in ("-m", "--multirun") for a in sys.argv[1:]):
        # before Hydra writes runs/<run_name>/.hydra: a run that is not ours is refused with nothing written; the
        # lock is held by this process until it exits (a sweep's jobs each claim their own -j<n> folder)
        cfg = configs[0]
        claim_run(cfg, Path(cfg.paths.checkpoints) / str(cfg.run_name), Path(cfg.paths.runs) / str(cfg.run_name))


@hydra.main(config_path="pkg://conf", config_name="train", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    run_cli(train, cfg, hydra_run_dir=True)


def main() -> None:
    """Check the command line before Hydra makes a run folder (one line and exit 2 on bad input), then run."""
    run_cli(_check_command_line)
    run_hydra(_hydra_main)  # a sweep runs every job, then reports the failed ones


if __name__ == "__main__":
    main()
