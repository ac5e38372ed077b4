"""``python -m eval env=left_turn agents='[always_proceed,ppo]' episodes=100 [split=validation|test|train]
[seed=...] [n_envs=2] [vec_env=batched]``

An evaluation owns its ``out_dir`` while it runs, as a training run owns its checkpoints
(:class:`av_gym.atomic.OwnedFolders`: an exclusive ``flock`` on ``out_dir/.lock``): a second ``python -m eval ...
out_dir=X`` is refused in one line, rather than both writing X and the second's rows replacing the first's. With an
``out_dir`` of its own, the run folder Hydra made under ``runs/eval/`` is removed again when it holds only Hydra's
files."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from av_gym.atomic import LOCK, OwnedFolders, lock_holder
from av_gym.errors import ConfigError, check_folder, discard_hydra_run_dir, folder_problem, run_cli, run_hydra

OUT_DIRS = OwnedFolders()  # the out_dirs this process is writing


def _plans(cfg: DictConfig) -> list:
    """Every agent spec planned and its checkpoint (if any) checked, before any env is built."""
    from omegaconf import OmegaConf

    from conf.check import validate_config
    from eval.agents import check_plan, check_sensor_overrides, plan_agent

    validate_config(cfg, "eval")
    episode_seeds(cfg)  # the seed range fits its split, before any agent is loaded
    duplicates = sorted({str(a) for a in cfg.agents if list(map(str, cfg.agents)).count(str(a)) > 1})
    if duplicates:  # one row would pool the same seeds twice and count each episode as two
        raise ConfigError(f"agents lists {duplicates[0]!r} more than once; each agent is one row over the same "
                          f"episode seeds, so list it once")
    sensors, shield = (OmegaConf.to_container(c, resolve=True) for c in (cfg.sensors, cfg.shield))
    plans = [plan_agent(spec, cfg.env.name, sensors, shield, cfg.paths.checkpoints) for spec in cfg.agents]
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    for plan in plans:
        check_plan(plan, cfg.env.name)
        check_sensor_overrides(plan, env_cfg)  # a trained agent's sensors with the command line's on top
        if cfg.get("vec_env", "subproc") == "batched":  # what the batched engine cannot run, before any folder
            from eval.batched import check_batched_plan

            check_batched_plan(plan, env_cfg)
    return plans


def episode_seeds(cfg: DictConfig) -> range:
    """The episodes' seeds: ``episodes`` consecutive seeds of ``split`` from ``seed`` (default the split's start);
    ConfigError naming the field when they leave the split (av_gym/seeds.py)."""
    from av_gym.seeds import config_seeds

    return config_seeds(str(cfg.split), int(cfg.episodes), cfg.seed, "seed")


def claim_out_dir(cfg: DictConfig) -> None:
    """``out_dir`` for this process alone (a lock held until the evaluation ends), then checked again under the
    lock: two evaluations started together both passed the check made before it. One line if another holds it."""
    out_dir = cfg.out_dir
    try:
        OUT_DIRS.take(out_dir)
    except BlockingIOError:
        pid = lock_holder(Path(out_dir) / LOCK)
        raise ConfigError(f"out_dir={out_dir}: another evaluation{f' (pid {pid})' if pid else ''} is writing it "
                          f"({Path(out_dir) / LOCK} is locked); wait for it, or pick another out_dir") from None
    except OSError as exc:
        raise ConfigError(f"out_dir={out_dir}: cannot be written: {os.strerror(exc.errno) if exc.errno else exc}") \
            from None
    problem = results_problem(cfg)
    if problem:
        OUT_DIRS.release(out_dir)
        raise ConfigError(problem)


def evaluate(cfg: DictConfig) -> list[dict]:
    """The evaluation ``cfg`` describes, in ``cfg.out_dir`` (held for this process while it runs); returns its rows."""
    try:
        return _evaluate(cfg)
    finally:
        OUT_DIRS.release(cfg.out_dir)
        _discard_unused_run_dir(cfg)


def _discard_unused_run_dir(cfg: DictConfig) -> None:
    """With an out_dir of its own, Hydra's run folder (``runs/eval/<env>-<time>/``) is left with only Hydra's files:
    removed, so that ``out_dir=X`` writes X alone. A folder with anything else is kept."""
    try:
        from hydra.core.hydra_config import HydraConfig

        run_dir = Path(HydraConfig.get().runtime.output_dir).resolve()
    except Exception:  # called from Python, not as a Hydra job
        return
    out = Path(cfg.out_dir).resolve()
    if out != run_dir and run_dir not in out.parents:
        discard_hydra_run_dir()


def _evaluate(cfg: DictConfig) -> list[dict]:
    from omegaconf import OmegaConf

    from av_gym.make import make_env
    from eval.agents import _is_path, resolve_agent
    from eval.report import write_results
    from eval.runner import EpisodeJob, run_episodes, run_episodes_parallel

    plans = _plans(cfg)
    if int(cfg.episodes) < 1:
        raise ConfigError(f"episodes must be >= 1, got {cfg.episodes}")
    problem = results_problem(cfg)  # before anything runs: another evaluation's results are not replaced
    if problem:
        raise ConfigError(problem)
    check_folder(cfg.out_dir, "out_dir", create=True)  # before the first episode: results must have somewhere to go
    claim_out_dir(cfg)  # ours alone until the evaluation ends
    seeds = episode_seeds(cfg)
    title = (f"{cfg.env.name} ({cfg.env.get('mode', '')}), {cfg.episodes} episodes of the {cfg.split} split "
             f"(seeds {seeds.start}..{seeds.stop - 1})")
    title = title.replace(" ()", "")
    env_name = cfg.env.name
    n_envs = int(cfg.get("n_envs", 1))
    rows = []
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    ran = {p.label: p.spec for p in plans if _is_path(p.spec)}  # trained agents: the checkpoint they resolved to
    for label, path in ran.items():
        print(f"[eval] {label}: {path}")
    for plan in plans:  # every spec is checked before any episode runs
        env = make_env(env_cfg, plan.sensors, plan.shield)
        _, policy = resolve_agent(plan.spec, env, env_name, cfg.paths.checkpoints)
        try:  # rows are appended episode by episode: Ctrl-C keeps (and writes) every finished episode
            if cfg.get("vec_env", "subproc") == "batched":  # n_envs episodes stepped together
                from eval.batched import run_episodes_batched

                env.close()
                run_episodes_batched(env_cfg, plan, policy, seeds, n_envs, plan.label, progress=cfg.progress_bar,
                                     out=rows)
            elif n_envs > 1:
                env.close()
                job = EpisodeJob(env_cfg, plan.sensors, plan.shield, plan.spec, env_name,
                                 str(cfg.paths.checkpoints), plan.label)
                run_episodes_parallel(job, seeds, n_envs, progress=cfg.progress_bar, out=rows)
            else:
                run_episodes(env, policy, seeds, plan.label, progress=cfg.progress_bar, out=rows)
                env.close()
        except KeyboardInterrupt:
            if rows:
                write_results(rows, cfg.out_dir, env_name, f"{title} (interrupted after {len(rows)} episodes)",
                              split=str(cfg.split))
                print(f"[eval] interrupted: the {len(rows)} episodes measured are in {cfg.out_dir}/results.csv",
                      file=sys.stderr)
            raise
        # each agent's rows as soon as it is done: an evaluation interrupted or failing later keeps what it measured
        write_results(rows, cfg.out_dir, env_name, title, split=str(cfg.split))
    table = write_results(rows, cfg.out_dir, env_name, title, sensors={p.label: p.sensors for p in plans},
                          checkpoints=ran, split=str(cfg.split))
    print(f"\n{title}\n\n{table}\n")
    print(f"[eval] per-episode rows: {cfg.out_dir}/results.csv   summary: {cfg.out_dir}/results.md")
    if env_name == "lane_keeping" and (cfg.get("plots") or cfg.get("videos")):
        from eval.plots import lane_keeping_figures

        paths = lane_keeping_figures(env_cfg, plans, cfg.out_dir, seeds.start, cfg.paths.checkpoints, str(cfg.split),
                                     bool(cfg.get("plots")), bool(cfg.get("videos")))
        print(f"[eval] figures (seed {seeds.start}): {', '.join(p.name for p in paths)}")
    if env_name == "left_turn" and cfg.get("videos"):
        from eval.plots import turn_videos

        paths = turn_videos(env_cfg, plans, cfg.out_dir, seeds.start, cfg.paths.checkpoints)
        print(f"[eval] videos (seed {seeds.start}): {', '.join(p.name for p in paths)}")
    return rows


def results_problem(cfg: DictConfig) -> str | None:
    """An ``out_dir`` that holds an evaluation's results is not written over unless ``overwrite=true``: a finished
    evaluation used to be replaced without a word. The default out_dir, Hydra's run folder, is new."""
    from pathlib import Path

    held = [name for name in ("results.csv", "results.md") if (Path(cfg.out_dir) / name).exists()]
    if held and not cfg.get("overwrite", False):
        return (f"out_dir={cfg.out_dir} already holds {' and '.join(held)} of an evaluation; pick another out_dir "
                f"(or leave it out: a new folder under runs/eval/), or replace them with overwrite=true")
    return None


def _check_command_line() -> None:
    from conf.check import _PLACEHOLDER, check_command_line

    configs = check_command_line("eval", sys.argv[1:])
    for cfg in configs:
        _plans(cfg)
        if cfg.out_dir != _PLACEHOLDER:  # the default, Hydra's run folder, was checked with hydra.run.dir
            problem = folder_problem(cfg.out_dir, "out_dir") or results_problem(cfg)
            if problem:
                raise ConfigError(problem)
    sweep = len(configs) != 1 or any(a in ("-m", "--multirun") for a in sys.argv[1:])
    if not sweep and configs[0].out_dir != _PLACEHOLDER:
        # before Hydra makes its run folder: an out_dir another evaluation is writing is refused with nothing
        # written; the lock is held by this process until the evaluation ends (a sweep's jobs each lock their own)
        claim_out_dir(configs[0])


@hydra.main(config_path="pkg://conf", config_name="eval", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    run_cli(evaluate, cfg, hydra_run_dir=True)


def main() -> None:
    """Check the command line before Hydra makes a run folder (one line and exit 2 on bad input), then run."""
    run_cli(_check_command_line)
    run_hydra(_hydra_main)  # a sweep runs every job, then reports the failed ones


if __name__ == "__main__":
    main()
