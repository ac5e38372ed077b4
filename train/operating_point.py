"""A GO/YIELD student's operating point: ``python -m train.operating_point checkpoints/<run> [--thresholds
[0.5,0.7,0.9]] [--episodes 300] [--write 0.8 --dest checkpoints/<run>-t0.8]``.

A student fitted to the oracle's labels by cross-entropy (``train/dagger.py``) outputs P(GO is safe | what it
sees); its deterministic choice GOes where that is above 0.5. Going only above a threshold τ is the same network
with ``log(τ / (1 - τ))`` taken off the GO logit's bias, so the result is still a plain PPO zip that
``python -m eval`` loads (issue 32: "a user can pick its operating point"). This tool evaluates thresholds on the
validation split (the same episodes for each threshold) and prints success and collision per
threshold (the per-env stack where the run's sensors need it, e.g. turn_perceived's tracker); ``--write τ`` saves
the student at τ into ``--dest`` (model.zip + config.yaml, ``agent.go_threshold`` recorded). Thresholds are absolute:
a run saved at its own ``agent.go_threshold`` is moved back to 0.5 first.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from av_gym.errors import ConfigError, run_cli
from conf.cli import Extend, ToolParser, items


def shift_go(model, threshold: float) -> float:
    """Move ``model``'s GO/YIELD decision boundary from P(GO) = 0.5 to ``threshold``: the GO logit's bias minus
    log(τ / (1 - τ)). Returns the shift applied (undo with ``shift_go(model, 1 - threshold)``)."""
    import torch as th

    from av_gym.wrappers import GO

    if not 0.0 < threshold < 1.0:
        raise ConfigError(f"threshold must be in (0, 1), got {threshold}")
    delta = math.log(threshold / (1.0 - threshold))
    with th.no_grad():
        model.policy.action_net.bias[GO] -= delta
    return delta


def evaluate(run_dir: Path, thresholds: list[float], episodes: int, first: int | None, n_envs: int = 128,
             zip_name: str = "model.zip") -> list:
    """(τ, collision, success) on ``episodes`` validation episodes for each threshold."""
    from agents.checkpoint import load_sb3, read_config_yaml
    from agents.ppo import SB3Policy
    from av_gym.seeds import config_seeds
    from eval.batched import play_on

    cfg = read_config_yaml(run_dir / "config.yaml")
    plain = [cfg["env"], cfg["sensors"], cfg["shield"]]
    agent = cfg["agent"]
    seeds = config_seeds("validation", episodes, first, "--seed")
    out, batched = [], _batchable(plain)
    for tau in thresholds:
        model = _at(load_sb3(run_dir / zip_name, device="cpu"), cfg, tau)
        policy = SB3Policy(model, int(agent.get("action_repeat", 1)), agent.get("actions", "env"))
        # a tracker (turn_perceived) or a shield: the per-env stack, as python -m eval runs it
        rows = play_on(*plain, policy, seeds, min(episodes, n_envs), f"t{tau}", batched)
        out.append((tau, float(np.mean([r["collision"] for r in rows])), float(np.mean([r["success"] for r in rows]))))
        print(f"| {tau:.2f} | {out[-1][1]:.3f} | {out[-1][2]:.3f} |", flush=True)
    return out


def _at(model, cfg: dict, tau: float):
    """``model`` (saved at its run's ``agent.go_threshold``, 0.5 if none) moved to the threshold ``tau``."""
    saved = float(cfg["agent"].get("go_threshold", 0.5))
    if saved != 0.5:
        shift_go(model, 1.0 - saved)  # back to the fit's own boundary: thresholds are absolute P(GO)
    shift_go(model, tau)
    return model


def _batchable(plain: list) -> bool:
    from av_gym.batched.vec_env import check_batchable

    try:
        check_batchable(*plain)
    except ConfigError:
        return False
    return True


def write(run_dir: Path, dest: Path, tau: float, zip_name: str = "model.zip") -> Path:
    """The student of ``run_dir`` at threshold ``tau`` into ``dest`` (model.zip, config.yaml)."""
    import yaml

    from agents.checkpoint import load_sb3, read_config_yaml
    from train.checkpoint import save_model_atomic, write_text_atomic

    cfg = read_config_yaml(run_dir / "config.yaml")
    model = _at(load_sb3(run_dir / zip_name, device="cpu"), cfg, tau)
    cfg["agent"]["go_threshold"] = float(tau)
    out = save_model_atomic(model, dest / "model.zip")
    write_text_atomic(dest / "config.yaml", yaml.safe_dump(cfg, sort_keys=False))
    return out


def main(argv: list[str] | None = None) -> None:
    import torch

    torch.set_num_threads(1)
    parser = ToolParser(prog="python -m train.operating_point", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="checkpoints/<run_name>/ of a go/yield DAgger (or PPO) run")
    parser.add_argument("--thresholds", type=items(float, low=0.01, high=0.99), nargs="+", action=Extend,
                        default=[0.5, 0.7, 0.8, 0.9], help="P(GO) thresholds, [0.5,0.9]")
    parser.add_argument("--episodes", type=int, default=300, help="validation episodes per threshold")
    parser.add_argument("--model", default="model.zip", choices=["model.zip", "best.zip", "latest.zip"],
                        help="which of the run's zips")
    parser.add_argument("--seed", type=int, default=None, help="first validation seed (default: the split's start)")
    parser.add_argument("--write", type=float, default=None, help="save the student at this threshold to --dest")
    parser.add_argument("--dest", default=None, help="folder for --write")
    args = parser.parse_args(argv)
    run_dir = Path(args.run_dir)
    for path in (run_dir / args.model, run_dir / "config.yaml"):
        if not path.is_file():
            raise ConfigError(f"{path} does not exist: run_dir must be a training run's checkpoint folder")
    if args.write is not None:
        if not args.dest or not 0 < args.write < 1:
            parser.error("--write needs a threshold in (0, 1) and --dest")
        print(f"[operating_point] {write(run_dir, Path(args.dest), args.write, args.model)}")
        return
    if args.episodes < 1:
        parser.error("--episodes must be >= 1")
    print("| P(GO) threshold | collision | success |\n|---:|---:|---:|")
    evaluate(run_dir, args.thresholds, args.episodes, args.seed, zip_name=args.model)


if __name__ == "__main__":
    run_cli(main)
