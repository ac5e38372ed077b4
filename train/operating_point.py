"""A GO/YIELD student's operating point: ``python -m train.operating_point checkpoints/<run> [--thresholds
[0.5,0.7,0.9]] [--episodes 300] [--write 0.8 --dest checkpoints/<run>-t0.8]``.

A student fitted to the oracle's labels by cross-entropy (``train/dagger.py``) outputs P(GO is safe | what it
sees); its deterministic choice GOes where that is above 0.5. Going only above a threshold τ is the same network
with ``log(τ / (1 - τ))`` taken off the GO logit's bias, so the result is still a plain PPO zip that
``python -m eval`` loads ("a user can pick its operating point"). This tool evaluates thresholds on the
validation split (the same episodes for each threshold) and prints success and collision per
threshold (the per-env stack where the run's sensors need it, e.g. turn_perceived's tracker), then the threshold
its ``--rule`` chooses (:func:`choose`: ``margin``, the largest success - collision; ``capped --max-collision c``,
the largest success at collisions <= c, e.g. the truth student's on the same episodes); ``--write τ`` saves
the student at τ into ``--dest`` (model.zip + config.yaml, ``agent.go_threshold`` recorded, and COMMAND: the run's
own followed by this command), under the folder's lock; a folder that holds files is replaced only with
``--overwrite``. Thresholds are absolute: a run saved at its own ``agent.go_threshold`` is moved back
to 0.5 first. The student must choose GO or YIELD (``agent.actions=go_yield``); a shipped reference's folder is
written only with ``--overwrite-reference`` (train/export.py: same scenario, actions, kind and sensors; the
folder's files replaced at once).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from av_gym.errors import ConfigError, run_cli
from av_gym.references import checkout_path_hint
from conf.cli import Extend, ToolParser, items, number


def shift_go(model, threshold: float) -> float:
    """Move ``model``'s GO/YIELD decision boundary from P(GO) = 0.5 to ``threshold``: the GO logit's bias minus
    log(τ / (1 - τ)). Returns the shift applied (undo with ``shift_go(model, 1 - threshold)``)."""
    import torch as th

    from av_gym.wrappers import GO

    if not 0.0 < threshold < 1.0:
        raise ConfigError(f"threshold must be in (0, 1), got {threshold}")
    n = getattr(getattr(model.policy, "action_net", None), "out_features", None)
    if n != 2:  # a steering or meta-action policy has no GO logit (one line here, not an IndexError later)
        raise ConfigError(f"the operating point is a GO/YIELD student's (agent.actions=go_yield: two logits); this "
                          f"policy has {n if n is not None else 'no discrete'} action outputs")
    delta = math.log(threshold / (1.0 - threshold))
    with th.no_grad():
        model.policy.action_net.bias[GO] -= delta
    return delta


def evaluate(run_dir: Path, thresholds: list[float], episodes: int, first: int | None, n_envs: int = 128,
             zip_name: str = "model.zip") -> list:
    """(τ, collision, success) on ``episodes`` validation episodes for each threshold, each row printed as it is
    measured, a progress bar while it is."""
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
        rows = play_on(*plain, policy, seeds, min(episodes, n_envs), f"P(GO) >= {tau:g}", batched,
                       progress=True)  # a threshold's 300 episodes on the per-env stack take minutes
        out.append((tau, float(np.mean([r["collision"] for r in rows])), float(np.mean([r["success"] for r in rows]))))
        print(f"| {tau:.2f} | {out[-1][1]:.3f} | {out[-1][2]:.3f} |", flush=True)
    return out


RULES = ("margin", "capped")
# Collision rates are shares of the same episodes (k / n); a cap typed as a decimal (0.026 for 26 / 1,000) must not
# fall on the wrong side of one by rounding.
_CAP_SLACK = 1e-9


def choose(rows: list[tuple[float, float, float]], rule: str = "margin",
           max_collision: float | None = None) -> tuple[float, str]:
    """The threshold ``rule`` picks from ``rows`` of (τ, collision, success), each a share of the same validation
    episodes, and why in words. ``margin``: the largest success - collision. ``capped``: the largest success among
    the thresholds whose collision is at most ``max_collision`` (a share; when none is, the fewest collisions).
    Ties go to fewer collisions, then to the higher τ (the more cautious student)."""
    if rule not in RULES:
        raise ConfigError(f"rule must be one of {list(RULES)}, got {rule!r}")
    if not rows:
        raise ConfigError("choose needs at least one measured threshold")
    if rule == "margin":
        best = max(rows, key=lambda r: (r[2] - r[1], -r[1], r[0]))
        return best[0], f"the largest success - collision, {best[2] - best[1]:.3f}"
    if max_collision is None or not 0.0 <= max_collision <= 1.0:
        raise ConfigError(f"rule=capped needs max_collision, a collision share in [0, 1], got {max_collision}")
    within = [r for r in rows if r[1] <= max_collision + _CAP_SLACK]
    if not within:
        best = min(rows, key=lambda r: (r[1], -r[2], -r[0]))
        return best[0], f"no threshold at collisions <= {max_collision:g}: the fewest, {best[1]:.3f}"
    best = max(within, key=lambda r: (r[2], -r[1], r[0]))
    return best[0], f"the largest success, {best[2]:.3f}, at collisions <= {max_collision:g}"


def at_fit_boundary(model, cfg: dict):
    """``model`` (saved at its config's ``agent.go_threshold``, 0.5 if none) moved back to its fit's own boundary,
    P(GO) 0.5: thresholds are absolute P(GO), so a saved student is shifted from there."""
    saved = float(cfg.get("agent", {}).get("go_threshold", 0.5))
    if saved != 0.5:
        shift_go(model, 1.0 - saved)
    return model


def _at(model, cfg: dict, tau: float):
    """``model`` (saved at its run's ``agent.go_threshold``, 0.5 if none) moved to the threshold ``tau``."""
    shift_go(at_fit_boundary(model, cfg), tau)
    return model


def _batchable(plain: list) -> bool:
    from av_gym.batched.vec_env import check_batchable

    try:
        check_batchable(*plain)
    except ConfigError:
        return False
    return True


def go_yield_problem(run_dir: Path, cfg: dict) -> str | None:
    """Why ``run_dir`` (config ``cfg``) has no operating point to choose, or None: only a GO/YIELD student does."""
    agent = cfg.get("agent") or {}
    actions = agent.get("actions", "env")
    if actions != "go_yield":
        env = (cfg.get("env") or {}).get("name", "?")
        return (f"run_dir={run_dir}: its agent chooses agent.actions={actions} on env={env}; the operating point is "
                f"a threshold on P(GO) of a GO/YIELD student (agent.actions=go_yield, e.g. dagger_turn, ppo_turn)")
    return None


def write(run_dir: Path, dest: Path, tau: float, zip_name: str = "model.zip", overwrite_reference: bool = False,
          command: str | None = None, overwrite: bool = False) -> Path:
    """The student of ``run_dir`` at threshold ``tau`` into ``dest`` (model.zip, config.yaml and COMMAND: the
    run's own followed by ``command``), the folder's files replaced at once under its lock; a folder holding files
    only with ``overwrite`` (:func:`train.export.dest_problem`), a shipped reference's folder only with
    ``overwrite_reference`` (:func:`train.export.reference_problem`)."""
    from agents.checkpoint import read_config_yaml
    from train.export import destination

    cfg = read_config_yaml(run_dir / "config.yaml")
    problem = go_yield_problem(run_dir, cfg)
    if problem:
        raise ConfigError(problem)
    command = command or (f"python -m train.operating_point {run_dir} --model {zip_name} --write {tau} --dest {dest}"
                          + (" --overwrite-reference" if overwrite_reference else "")
                          + (" --overwrite" if overwrite else ""))
    with destination(run_dir, dest, cfg, "python -m train.operating_point", overwrite, overwrite_reference,
                     True) as keep_others:
        _write_student(run_dir, dest, cfg, tau, zip_name, command, keep_others)
    return dest / "model.zip"


def _write_student(run_dir: Path, dest: Path, cfg: dict, tau: float, zip_name: str, command: str,
                   keep_others: bool) -> None:
    """The files of :func:`write`, into ``dest`` (held by this process)."""
    import yaml

    from agents.checkpoint import load_sb3
    from train.export import write_checkpoint_folder

    model = _at(load_sb3(run_dir / zip_name, device="cpu"), cfg, tau)
    cfg["agent"]["go_threshold"] = float(tau)
    source = (run_dir / "COMMAND").read_text() if (run_dir / "COMMAND").is_file() else ""
    provenance = (source.rstrip("\n") + "\n" if source.strip() else
                  f"# {run_dir}: no COMMAND (its config.yaml has the training settings)\n")
    provenance += f"# then, P(GO) >= {tau} from {run_dir / zip_name}:\n{command}\n"
    write_checkpoint_folder(dest, {"model.zip": lambda p: model.save(str(p)),
                                   "config.yaml": yaml.safe_dump(cfg, sort_keys=False), "COMMAND": provenance},
                            keep_others)


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
    parser.add_argument("--rule", default="margin", choices=list(RULES),
                        help="how the threshold is chosen from the table: margin, the largest success - collision; "
                             "capped, the largest success at collisions <= --max-collision")
    parser.add_argument("--max-collision", type=number(float, low=0.0, high=1.0), default=None,
                        help="--rule capped's cap on the validation collision share, e.g. the truth student's on "
                             "the same episodes (python -m eval ... split=validation)")
    parser.add_argument("--write", type=float, default=None, help="save the student at this threshold to --dest")
    parser.add_argument("--dest", default=None, help="folder for --write (a shipped reference's: only with "
                                                     "--overwrite-reference)")
    parser.add_argument("--overwrite-reference", action="store_true",
                        help="allow --dest to be a shipped reference agent's folder: replaced (model, config and "
                             "COMMAND at once) by a student of the same scenario, actions, kind and sensors")
    parser.add_argument("--overwrite", action="store_true",
                        help="allow --dest to hold files (an earlier student's, another run's): all of them replaced")
    args = parser.parse_args(argv)
    run_dir = Path(args.run_dir)
    for path in (run_dir / args.model, run_dir / "config.yaml"):
        if not path.is_file():
            raise ConfigError(f"{path} does not exist: run_dir must be a training run's checkpoint folder"
                              f"{checkout_path_hint(run_dir, by_name=False)}")
    from agents.checkpoint import read_config_yaml

    problem = go_yield_problem(run_dir, read_config_yaml(run_dir / "config.yaml"))
    if problem:  # before any episode (a lane keeper has no GO logit: one line, not an IndexError mid-run)
        raise ConfigError(problem)
    if args.write is not None:
        if not args.dest or not 0 < args.write < 1:
            parser.error("--write needs a threshold in (0, 1) and --dest")
        import shlex

        command = "python -m train.operating_point " + " ".join(shlex.quote(a) for a in (
            argv if argv is not None else sys.argv[1:]))
        out = write(run_dir, Path(args.dest), args.write, args.model, args.overwrite_reference, command,
                    args.overwrite)
        print(f"[operating_point] {out}, with config.yaml and COMMAND")
        return
    if args.episodes < 1:
        parser.error("--episodes must be >= 1")
    if (args.rule == "capped") != (args.max_collision is not None):
        parser.error("--max-collision goes with --rule capped (the cap on validation collisions), and only with it")
    print("| P(GO) threshold | collision | success |\n|---:|---:|---:|")
    rows = evaluate(run_dir, args.thresholds, args.episodes, args.seed, zip_name=args.model)
    tau, why = choose(rows, args.rule, args.max_collision)
    print(f"[operating_point] rule {args.rule}: P(GO) >= {tau:g} ({why})")


if __name__ == "__main__":
    run_cli(main)
