"""``python -m eval env=left_turn agents='[always_proceed,ppo]' episodes=100 seed=1000``"""

from __future__ import annotations


import hydra
from omegaconf import DictConfig

from av_gym.errors import ConfigError, run_cli


def evaluate(cfg: DictConfig) -> list[dict]:
    from omegaconf import OmegaConf

    from av_gym.make import make_env
    from eval.agents import plan_agent, resolve_agent
    from eval.report import write_results
    from eval.runner import run_episodes

    if int(cfg.episodes) < 1:
        raise ConfigError(f"episodes must be >= 1, got {cfg.episodes}")
    env_name = cfg.env.name
    rows = []
    seeds = range(int(cfg.seed), int(cfg.seed) + int(cfg.episodes))
    sensors, shield = (OmegaConf.to_container(c, resolve=True) for c in (cfg.sensors, cfg.shield))
    plans = [plan_agent(spec, env_name, sensors, shield, cfg.paths.checkpoints) for spec in cfg.agents]
    for plan in plans:  # every spec is checked before any episode runs
        env = make_env(cfg.env, plan.sensors, plan.shield)
        _, policy = resolve_agent(plan.spec, env, env_name, cfg.paths.checkpoints)
        rows += run_episodes(env, policy, seeds, plan.label, progress=cfg.progress_bar)
        env.close()
    title = f"{env_name} ({cfg.env.get('mode', '')}), {cfg.episodes} episodes from seed {cfg.seed}".replace(" ()", "")
    table = write_results(rows, cfg.out_dir, env_name, title)
    print(f"\n{title}\n\n{table}\n")
    print(f"[eval] per-episode rows: {cfg.out_dir}/results.csv   summary: {cfg.out_dir}/results.md")
    if env_name == "lane_keeping" and (cfg.get("plots") or cfg.get("videos")):
        from eval.plots import lane_keeping_figures

        paths = lane_keeping_figures(cfg, plans, cfg.out_dir, bool(cfg.get("plots")), bool(cfg.get("videos")))
        print(f"[eval] figures (seed {cfg.seed}): {', '.join(p.name for p in paths)}")
    return rows


@hydra.main(config_path="pkg://conf", config_name="eval", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run_cli(evaluate, cfg)


if __name__ == "__main__":
    main()
