"""Export a trained PPO run as a reference checkpoint: ``python -m train.export checkpoints/<run>
checkpoints/reference/<name> [--best]``.

Writes ``<dest>/model.zip`` (the run's ``model.zip``, or ``best.zip`` with ``--best``) without the optimizer's
state, and the run's ``config.yaml`` beside it. Why drop the optimizer: Adam keeps two moments per weight, two
thirds of an SB3 zip; a reference checkpoint is for ``python -m eval``, which never steps an optimizer (resuming
training reads the run's own folder). The policy's weights, and so its actions, are unchanged."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from av_gym.errors import ConfigError, run_cli


def export_reference(run_dir: str | Path, dest: str | Path, best: bool = False) -> Path:
    """Copy run ``run_dir``'s policy (``model.zip`` or ``best.zip``) and ``config.yaml`` to ``dest``; returns the
    written zip."""
    from stable_baselines3 import PPO

    from train.checkpoint import save_model_atomic

    run_dir, dest = Path(run_dir), Path(dest)
    src = run_dir / ("best.zip" if best else "model.zip")
    for path in (src, run_dir / "config.yaml"):
        if not path.is_file():
            raise ConfigError(f"{path} does not exist: run_dir must be a training run's checkpoint folder "
                              f"(checkpoints/<run_name>/ with model.zip{', best.zip' if best else ''} and config.yaml)")
    model = PPO.load(str(src), device="cpu")
    policy = model.policy
    policy.optimizer = policy.optimizer_class(policy.parameters(), lr=model.lr_schedule(1.0),
                                              **policy.optimizer_kwargs)  # fresh: no moments
    dest.mkdir(parents=True, exist_ok=True)
    out = save_model_atomic(model, dest / "model.zip")
    shutil.copyfile(run_dir / "config.yaml", dest / "config.yaml")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m train.export", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="checkpoints/<run_name>/ of a PPO training run")
    parser.add_argument("dest", help="folder to write, e.g. checkpoints/reference/<agent>")
    parser.add_argument("--best", action="store_true", help="export best.zip (the best periodic evaluation)")
    args = parser.parse_args(argv)
    out = export_reference(args.run_dir, args.dest, args.best)
    print(f"[export] {out} ({out.stat().st_size / 1e6:.1f} MB) and config.yaml")


if __name__ == "__main__":
    run_cli(main)
