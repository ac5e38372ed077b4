"""PilotNet behaviour cloning: a thin trainer that reads ``cfg.agent`` and runs :func:`agents.bc.train`.

The agent's ``sensors`` field (``cameras``) names the sensors preset it is trained and evaluated with; it replaces
the train default (``truth``, which has no images) unless the command line already chose a preset with cameras.
The checkpoint's ``config.yaml`` is rewritten with that preset, so ``python -m eval`` builds the camera env for it.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

AGENT_KEYS = ("name", "kind", "scenarios", "sensors")  # the rest are agents.bc.Args fields


def _args(cfg: DictConfig):
    from agents.bc import Args

    agent = OmegaConf.to_container(cfg.agent, resolve=True)
    settings = {k: v for k, v in agent.items() if k not in AGENT_KEYS}
    settings.setdefault("seed", int(cfg.seed))
    return Args.from_mapping(settings)


def _sensors(cfg: DictConfig) -> dict:
    """The sensors preset PilotNet uses: the command line's if it has cameras, else the agent's own."""
    from eval.agents import compose_group

    sensors = OmegaConf.to_container(cfg.sensors, resolve=True)
    if "cameras" in sensors:
        return sensors
    return compose_group("sensors", str(cfg.agent.get("sensors", "cameras")))


def validate(cfg: DictConfig) -> list[str]:
    """Problems with ``cfg.agent`` for PilotNet, as one-line messages (empty if none)."""
    try:
        args = _args(cfg)
    except (TypeError, ValueError) as exc:
        return [str(exc)]
    problems = args.problems()
    if cfg.env.name != "lane_keeping":
        problems.append(f"agent pilotnet drives env=lane_keeping, not env={cfg.env.name}")
    try:
        if "cameras" not in _sensors(cfg):
            problems.append(f"agent.sensors={cfg.agent.get('sensors')!r} gives no cameras; PilotNet needs a "
                            f"preset with cameras (e.g. cameras)")
    except ValueError as exc:
        problems.append(f"agent.sensors: {exc}")
    return problems


def train_pilotnet(cfg: DictConfig, ckpt_dir: Path, run_dir: Path) -> Path:
    """Collect demonstrations, train, write ``ckpt_dir/model.pt`` (best validation loss) and ``config.yaml``
    (with the camera sensors preset); returns the model path."""
    from agents.bc import train
    from train.checkpoint import write_text_atomic

    sensors = _sensors(cfg)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    resolved["sensors"] = sensors
    write_text_atomic(Path(ckpt_dir) / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(resolved)))
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    return train(_args(cfg), env_cfg, sensors, run_dir, ckpt_dir)
