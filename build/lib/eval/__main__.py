"""``python -m eval env=left_turn agents='[always_proceed,ppo]' episodes=100 [split=validation|test|train]
[seed=...] [n_envs=2] [vec_env=batched]``"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from av_gym.errors import ConfigError, check_folder, folder_problem, run_cli


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


def evaluate(cfg: DictConfig) -> list[dict]:
    from omegaconf import OmegaConf

    from av_gym.make import make_env
    from eval.agents import _is_path, resolve_agent
    from eval.report import write_results
    from eval.runner import EpisodeJob, run_episodes, run_episodes_parallel

    plans = _plans(cfg)
    if int(cfg.episodes) < 1:
        raise ConfigError(f"episodes must be >= 1, got {cfg.episodes}")
    check_folder(cfg.out_dir, "out_dir", create=True)  # before the first episode: results must have somewhere to go
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
            if cfg.get("vec_env", "subproc") == "batched":  # issue 16: n_envs episodes stepped together
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

        paths = lane_keeping_figures(cfg, plans, cfg.out_dir, bool(cfg.get("plots")), bool(cfg.get("videos")))
        print(f"[eval] figures (seed {seeds.start}): {', '.join(p.name for p in paths)}")
    if env_name == "left_turn" and cfg.get("videos"):
        from eval.plots import turn_videos

        paths = turn_videos(cfg, plans, cfg.out_dir)
        print(f"[eval] videos (seed {seeds.start}): {', '.join(p.name for p in paths)}")
    return rows


def _check_command_line() -> None:
    from conf.check import _PLACEHOLDER, check_command_line

    for cfg in check_command_line("eval", sys.argv[1:]):
        _plans(cfg)
        if cfg.out_dir != _PLACEHOLDER:  # the default, Hydra's run folder, was checked with hydra.run.dir
            problem = folder_problem(cfg.out_dir, "out_dir")
            if problem:
                raise ConfigError(problem)


@hydra.main(config_path="pkg://conf", config_name="eval", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    run_cli(evaluate, cfg, hydra_run_dir=True)


def main() -> None:
    """Check the command line before Hydra makes a run folder (one line and exit 2 on bad input), then run."""
    run_cli(_check_command_line)
    _hydra_main()


if __name__ == "__main__":
    main()
