"""Export a trained PPO run as a reference checkpoint: ``python -m train.export checkpoints/<run>
checkpoints/reference/<name> [--best] [--command "python -m train ..."]``.

Writes ``<dest>/model.zip`` (the run's ``model.zip``, or ``best.zip`` with ``--best``) without the optimizer's
state, the run's ``config.yaml`` beside it, and ``COMMAND`` (the command that trained it; every reference folder
has one, ``tests/test_reference_checkpoints.py``). Why drop the optimizer: Adam keeps two moments per weight, two
thirds of an SB3 zip; a reference checkpoint is for ``python -m eval``, which never steps an optimizer (resuming
training reads the run's own folder). The policy's weights, and so its actions, are unchanged."""

from __future__ import annotations

from pathlib import Path

from av_gym.errors import ConfigError, run_cli
from conf.cli import Extend, ToolParser, items


def export_reference(run_dir: str | Path, dest: str | Path, best: bool = False, command: str | None = None) -> Path:
    """Copy run ``run_dir``'s policy (``model.zip`` or ``best.zip``) and ``config.yaml`` to ``dest``, and write
    ``command`` to ``dest/COMMAND`` if given; returns the written zip. Every file is written atomically."""
    from agents.checkpoint import load_sb3
    from train.checkpoint import save_model_atomic, write_text_atomic

    run_dir, dest = Path(run_dir), Path(dest)
    src = run_dir / ("best.zip" if best else "model.zip")
    for path in (src, run_dir / "config.yaml"):
        if not path.is_file():
            raise ConfigError(f"{path} does not exist: run_dir must be a training run's checkpoint folder "
                              f"(checkpoints/<run_name>/ with model.zip{', best.zip' if best else ''} and config.yaml)")
    model = load_sb3(src, device="cpu")  # one line for an empty, truncated or corrupt zip
    policy = model.policy
    policy.optimizer = policy.optimizer_class(policy.parameters(), lr=model.lr_schedule(1.0),
                                              **policy.optimizer_kwargs)  # fresh: no moments
    dest.mkdir(parents=True, exist_ok=True)
    out = save_model_atomic(model, dest / "model.zip")
    write_text_atomic(dest / "config.yaml", (run_dir / "config.yaml").read_text())
    if command:
        write_text_atomic(dest / "COMMAND", command.rstrip("\n") + "\n")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = ToolParser(prog="python -m train.export", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="checkpoints/<run_name>/ of a PPO training run")
    parser.add_argument("dest", help="folder to write, e.g. checkpoints/reference/<agent>")
    parser.add_argument("--best", action="store_true", help="export best.zip (the best periodic evaluation)")
    parser.add_argument("--command", help="the command that trained the run, written to DEST/COMMAND")
    args = parser.parse_args(argv)
    out = export_reference(args.run_dir, args.dest, args.best, args.command)
    print(f"[export] {out} ({out.stat().st_size / 1e6:.1f} MB) and config.yaml")
    if not (out.parent / "COMMAND").is_file():
        print(f"[export] {out.parent}/COMMAND is missing: write the command that trained the run there "
              f"(--command), as every reference checkpoint has")


if __name__ == "__main__":
    run_cli(main)
