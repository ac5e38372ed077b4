"""Student forms screened offline on a DAgger run's labels: ``python -m train.dagger_forms checkpoints/<run>
--set agent.net_arch=[256,256,256] [--refits 3] [--epochs 8] [--episodes 200] [--out runs/forms/x.json]``.

A DAgger run's ``latest.zip`` holds every state its students visited with the teacher's label (the aggregate,
train/dagger.py). Fitting another student form on that aggregate (a wider or deeper network, the disagreement
weights) and driving it on the validation split asks what the form buys on the same data, for the price of a
few refits instead of a new DAgger run (whose labelling is 85 % of its time, docs/dagger.md). The student is
built from the run's own config.yaml with ``--set`` overrides (``agent.*`` fields of
:class:`agents.dagger.DaggerParams`), fitted from scratch ``--refits`` times ``--epochs`` epochs by DAgger's
own :func:`train.dagger.fit` (agent.disagree_weight recomputed before each refit, as each DAgger round does),
then driven at its ``agent.go_threshold`` on ``--episodes`` validation episodes on the batch. What a screen
cannot say: the states are those the run's own students visited, so a form that would drive elsewhere is judged
on another student's states; its DAgger run is the test of a form that pays here.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from av_gym.errors import ConfigError, run_cli
from conf.cli import ToolParser


def student_config(run_dir: Path, overrides: list[str]) -> dict:
    """The run's config.yaml with ``overrides`` (``agent.key=value``, Hydra's value syntax) applied; the agent
    checked as :class:`agents.dagger.DaggerParams` (one line naming a bad field)."""
    from omegaconf import OmegaConf

    from agents.checkpoint import read_config_yaml
    from agents.dagger import DaggerParams

    cfg = OmegaConf.create(read_config_yaml(run_dir / "config.yaml"))
    for item in overrides:
        key = item.split("=", 1)[0]
        if "=" not in item or not key.startswith("agent.") or OmegaConf.select(cfg, key) is None \
                and key[len("agent."):] not in DaggerParams.__dataclass_fields__:
            raise ConfigError(f"--set takes agent.<field>=<value> of a DAgger agent (agents/dagger.py "
                              f"DaggerParams), got {item!r}")
    cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(overrides))
    plain = OmegaConf.to_container(cfg, resolve=True)
    DaggerParams.from_mapping(plain["agent"], where="agent")
    return plain


def screen(run_dir: Path, overrides: list[str], refits: int, epochs: int, episodes: int, seed: int,
           holdout: float = 0.0, lr_end: float | None = None) -> dict:
    """Fit the form ``overrides`` on ``run_dir``'s aggregate and validate it; the row (labels, fit accuracy,
    validation collision and success, process CPU seconds of the fit and of the validation). ``holdout``: that
    share of the aggregate's episodes is kept out of the fit and scored after each refit (or epoch), so a fit is
    told from memorisation; ``lr_end``: the step falls from agent.fit_lr to it over all epochs (cosine, one refit
    an epoch: Adam's state carried on). ``episodes`` 0: no validation drive."""
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from train.dagger import read_aggregate, student_model, unpack_rounds

    cfg = student_config(run_dir, overrides)
    agent, plain = cfg["agent"], [cfg["env"], cfg["sensors"], cfg["shield"]]
    data = read_aggregate(run_dir / "latest.zip", unpack_rounds)
    fitted, held = _split(data, holdout, seed)
    repeat, actions = int(agent["action_repeat"]), str(agent["actions"])
    env = BatchedLeftTurnVecEnv(*plain, 2, action_repeat=repeat, actions=actions,
                                timeout_is_terminal=bool(agent["timeout_is_terminal"]), pool=0)
    model = student_model(env, agent, seed, "cpu")
    env.close()
    t0 = time.process_time()
    curve = _fit_curve(model, agent, fitted, held, refits, epochs, seed, lr_end)
    t1 = time.process_time()
    row = {"run": str(run_dir), "set": overrides, "labels": len(data.labels), "refits": refits, "epochs": epochs,
           "seed": seed, "parameters": sum(p.numel() for p in model.policy.parameters()),
           "fit_accuracy": curve[-1]["fit"], "val_episodes": episodes, "fit_cpu_s": round(t1 - t0, 1)}
    if held is not None:
        row.update(holdout=holdout, held_labels=len(held.labels), held_accuracy=curve[-1]["held"], lr_end=lr_end,
                   curve=curve)
    if episodes > 0:
        row["val_collision"], row["val_success"] = _drive(model, agent, plain, episodes)
        row["val_cpu_s"] = round(time.process_time() - t1, 1)
    return row


def _split(data, holdout: float, seed: int):
    """The aggregate, or (with ``holdout`` > 0) its states outside and inside a held-out share of its episodes
    (train/observation_ceiling.py tells the episodes apart)."""
    import numpy as np

    from train.dagger import Round
    from train.observation_ceiling import elapsed_column, episode_ids, holdout_mask

    if holdout == 0:
        return data, None
    turn = {"turn": np.stack([o["turn"] for o in data.obs])} if "turn" in data.obs[0] else {}
    elapsed = elapsed_column(turn)
    mask = holdout_mask(episode_ids(elapsed), holdout, seed)

    def part(keep) -> Round:
        idx = np.flatnonzero(keep)
        return Round(obs=[data.obs[i] for i in idx], labels=[data.labels[i] for i in idx],
                     returns=[data.returns[i] for i in idx], targets=[data.targets[i] for i in idx] if data.targets
                     else [])
    return part(~mask), part(mask)


def _fit_curve(model, agent: dict, fitted, held, refits: int, epochs: int, seed: int,
               lr_end: float | None) -> list[dict]:
    """DAgger's refit ``refits`` times ``epochs`` epochs (with ``lr_end``: one epoch a refit on a cosine step);
    after each, the accuracy on the fitted labels and on ``held`` (None: not scored)."""
    import math

    from train.dagger import fit

    lr0, total = float(agent["fit_lr"]), refits * epochs
    plan = ([(epochs, lr0, seed * 1000 + k) for k in range(refits)] if lr_end is None else
            [(1, lr_end + 0.5 * (lr0 - lr_end) * (1 + math.cos(math.pi * e / max(total - 1, 1))), seed * 1000 + e)
             for e in range(total)])
    curve = []
    for n, lr, stream in plan:
        accuracy = fit(model, fitted, n, int(agent["fit_batch"]), lr, stream,
                       float(agent.get("disagree_weight", 1.0)))
        curve.append({"epochs": n * (len(curve) + 1), "lr": lr, "fit": round(accuracy, 4),
                      "held": round(accuracy_on(model, held), 4) if held is not None else None})
        print(f"[forms] epoch {curve[-1]['epochs']}: step {lr:.2e}, fit {curve[-1]['fit']:.4f}, held-out "
              f"{curve[-1]['held']}", flush=True)  # a long fit's progress, one line an epoch (or refit)
    return curve


def accuracy_on(model, data) -> float:
    """The share of ``data``'s labels that ``model`` (its most likely choice) matches."""
    import numpy as np

    from train.dagger import student_choices

    return float(np.mean(student_choices(model, data) == np.asarray(data.labels)))


def _drive(model, agent: dict, plain: list, episodes: int) -> tuple[float, float]:
    """Validation (collision, success) on ``episodes`` validation episodes on the batch, at agent.go_threshold."""
    from agents.dagger import DaggerParams
    from conf.commands import TrainOptions
    from train.dagger import _operating_point, _validation

    _operating_point(DaggerParams.from_mapping(agent, where="agent"))(model, True)
    validation = _validation(TrainOptions(eval_n=episodes), plain, int(agent["action_repeat"]),
                             str(agent["actions"]), True)
    return validation(model)


def main(argv: list[str] | None = None) -> None:
    import torch

    from train.checkpoint import write_text_atomic

    torch.set_num_threads(1)
    parser = ToolParser(prog="python -m train.dagger_forms", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="checkpoints/<run_name>/ of a DAgger run (its latest.zip and config.yaml)")
    parser.add_argument("--set", nargs="*", default=[], help="agent.<field>=<value> overrides of the student")
    parser.add_argument("--refits", type=int, default=3, help="fits from scratch on the whole aggregate")
    parser.add_argument("--epochs", type=int, default=8, help="epochs per refit")
    parser.add_argument("--episodes", type=int, default=200, help="validation episodes (the split's first); 0: none")
    parser.add_argument("--seed", type=int, default=1, help="the student's initial weights and minibatch order")
    parser.add_argument("--holdout", type=float, default=0.0,
                        help="share of the aggregate's episodes kept out of the fit and scored (0: none)")
    parser.add_argument("--lr-end", type=float, default=None,
                        help="the fit's step falls from agent.fit_lr to this over all epochs (cosine)")
    parser.add_argument("--out", default=None, help="write the row as JSON here (a file that exists is refused)")
    args = parser.parse_args(argv)
    for name in ("refits", "epochs"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.episodes < 0 or not 0 <= args.holdout < 1 or args.lr_end is not None and args.lr_end <= 0:
        parser.error(f"--episodes must be >= 0, --holdout in [0, 1), --lr-end > 0; got {args.episodes}, "
                     f"{args.holdout}, {args.lr_end}")
    if args.out and Path(args.out).exists():
        parser.error(f"--out {args.out} exists: another screen's row; choose another file")
    row = screen(Path(args.run_dir), list(args.set), args.refits, args.epochs, args.episodes, args.seed,
                 args.holdout, args.lr_end)
    print(json.dumps(row))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.out), json.dumps(row, indent=1) + "\n")


if __name__ == "__main__":
    run_cli(main)
