"""The recurrent student (agents/recurrent.py) fitted offline on a DAgger run's aggregate, whole episodes in decision
order: ``python -m train.dagger_recurrent checkpoints/<run> [--holdout 0.1] [--epochs 12] [--lr-end 1e-5]
[--hidden 64] [--set agent.attention_dim=128 ...] [--episodes 300] [--seed 1] [--out runs/x.json] [--save checkpoints/<name>/student.pt]``.

The question (docs/dagger.md, "Student forms"): does the decision history hold more about the planner's label than
the observation of the decision, whose memory features already summarise every indicator reading? DAgger stores its
labelled states episode by episode, each episode's decisions in order (train/dagger.py ``Round.close``), so the
aggregate holds every history: an episode starts where the elapsed-time feature restarts at 0
(:func:`train.observation_ceiling.episode_ids`), and one that does not start at 0 or skips a decision is refused.
The held-out episodes are those ``python -m train.dagger_forms <run> --holdout <share> --seed <seed>`` keeps out
(the same :func:`train.observation_ceiling.holdout_mask`), so held-out accuracies compare across the two tools.

The fit: Adam on the labels' cross-entropy over every decision of ``--batch-episodes`` episodes a step (10
episodes: ~254 decisions, DAgger's ``fit_batch`` of 256 states), one pass over the fitted episodes an epoch in an
order drawn from a generator seeded ``--seed``, the step falling from the run's ``agent.fit_lr`` to ``--lr-end``
on a cosine over the epochs (as ``dagger_forms --lr-end``); after each epoch the accuracy (P(GO) >= 0.5 against
the label) on the fitted and the held-out episodes. ``--hidden 0`` fits the same code without its GRU (the
feed-forward control). Then the fitted student drives ``--episodes`` validation episodes on the batch at the run's
``agent.go_threshold`` (the curve's 300: seeds 1,000,000+).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from av_gym.errors import ConfigError, run_cli
from conf.cli import ToolParser


@dataclass
class Episodes:
    """An aggregate's decisions, episode by episode: ``obs[key]`` (N, ...) and ``labels`` (N,) in stored order;
    ``index`` (E, T): each episode's decisions in order, -1 past its end."""

    obs: dict[str, np.ndarray]
    labels: np.ndarray
    index: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.index >= 0

    def take(self, which: np.ndarray) -> "Episodes":
        """The episodes ``which`` (indices into the first axis of ``index``), sharing the arrays."""
        return Episodes(self.obs, self.labels, self.index[which])

    def batch(self, which: np.ndarray):
        """Tensors of the episodes ``which``: observations (B, T, ...), labels (B, T), valid (B, T)."""
        import torch as th

        idx = self.index[which]
        t = int(max(1, (idx >= 0).sum(axis=1).max()))
        idx = idx[:, :t]
        safe = np.maximum(idx, 0)
        x = {k: th.as_tensor(v[safe]) for k, v in self.obs.items()}
        return x, th.as_tensor(self.labels[safe]), th.as_tensor(idx >= 0)


def episode_index(elapsed: np.ndarray) -> np.ndarray:
    """(E, T) the stored positions of each episode's decisions (-1 past its end) from the elapsed-time feature;
    a ConfigError unless every episode starts at 0 and grows by one decision period (the aggregate's decisions in
    order, none missing)."""
    from train.observation_ceiling import episode_ids

    elapsed = np.asarray(elapsed, dtype=np.float64)
    ids = episode_ids(elapsed)
    starts = np.flatnonzero(np.concatenate([[True], np.diff(ids) > 0]))
    steps = np.diff(elapsed)[np.diff(ids) == 0]
    period = float(np.median(steps)) if len(steps) else 1.0
    if np.any(np.abs(elapsed[starts]) > 1e-6) or np.any(np.abs(steps - period) > 1e-3 * period):
        raise ConfigError("the aggregate does not keep each episode's decisions in order from its start (an episode "
                          "starting after 0, or a decision missing): a recurrent student cannot be fitted on it")
    lengths = np.diff(np.append(starts, len(elapsed)))
    t = np.arange(int(lengths.max()))
    return np.where(t[None] < lengths[:, None], starts[:, None] + t[None], -1)


def load_episodes(run_dir: Path) -> Episodes:
    """``run_dir``'s aggregate (latest.zip) as :class:`Episodes` (one line if it holds none, or out of order)."""
    import io

    from train.dagger import read_aggregate
    from train.observation_ceiling import elapsed_column

    raw = read_aggregate(run_dir / "latest.zip", lambda b: dict(np.load(io.BytesIO(b))))
    obs = {k[len("obs:"):]: np.asarray(v, dtype=np.float32) for k, v in raw.items() if k.startswith("obs:")}
    return Episodes(obs, np.asarray(raw["labels"], dtype=np.int64), episode_index(elapsed_column(obs)))


def split_episodes(data: Episodes, holdout: float, seed: int) -> tuple[Episodes, Episodes | None]:
    """The fitted and held-out episodes: those ``dagger_forms --holdout`` keeps out at the same ``seed``."""
    from train.observation_ceiling import holdout_mask

    if holdout == 0:
        return data, None
    # dagger_forms draws from the episode ids 0..E-1 of episode_ids, which number the episodes as index's rows
    held = holdout_mask(np.arange(len(data.index)), holdout, seed)
    return data.take(np.flatnonzero(~held)), data.take(np.flatnonzero(held))


def accuracy(student, data: Episodes, chunk: int = 256) -> float:
    """The share of ``data``'s decisions where the student's argmax (P(GO) >= 0.5) is the label."""
    import torch as th

    right, total = 0, 0
    student.eval()
    with th.no_grad():
        for i in range(0, len(data.index), chunk):
            x, y, valid = data.batch(np.arange(i, min(i + chunk, len(data.index))))
            choice = student(x, valid).argmax(-1)
            right += int(((choice == y) & valid).sum())
            total += int(valid.sum())
    return right / max(total, 1)


def fit(student, data: Episodes, held: Episodes | None, epochs: int, batch_episodes: int, lr: float,
        lr_end: float, seed: int) -> list[dict]:
    """Adam on the masked cross-entropy, the step on a cosine from ``lr`` to ``lr_end`` over ``epochs``; one row
    per epoch (step, fitted and held-out accuracy, CPU-s)."""
    import torch as th

    th.manual_seed(seed)
    rng = np.random.default_rng(seed)
    opt = th.optim.Adam(student.parameters(), lr=lr)
    curve = []
    for epoch in range(epochs):
        step = lr_end + 0.5 * (lr - lr_end) * (1 + math.cos(math.pi * epoch / max(epochs - 1, 1)))
        for group in opt.param_groups:
            group["lr"] = step
        t0 = time.process_time()
        _epoch(student, data, opt, rng.permutation(len(data.index)), batch_episodes)
        curve.append({"epoch": epoch + 1, "lr": step, "fit_cpu_s": round(time.process_time() - t0, 1),
                      "fit": round(accuracy(student, data), 4),
                      "held": round(accuracy(student, held), 4) if held is not None else None})
        print(f"[recurrent] epoch {epoch + 1}: step {step:.2e}, fit {curve[-1]['fit']:.4f}, held-out "
              f"{curve[-1]['held']} ({curve[-1]['fit_cpu_s']} CPU-s)", flush=True)
    return curve


def _epoch(student, data: Episodes, opt, order: np.ndarray, batch_episodes: int) -> None:
    """One pass over ``data``'s episodes in ``order``, ``batch_episodes`` a step."""
    import torch as th

    student.train()
    for i in range(0, len(order), batch_episodes):
        x, y, valid = data.batch(order[i:i + batch_episodes])
        logits = student(x, valid)
        loss = th.nn.functional.cross_entropy(logits[valid], y[valid])
        opt.zero_grad()
        loss.backward()
        opt.step()


def screen(run_dir: Path, hidden: int, epochs: int, lr_end: float, holdout: float, episodes: int, seed: int,
           batch_episodes: int = 10, save: Path | None = None, overrides: list[str] | None = None) -> dict:
    """Fit a recurrent student (``hidden`` 0: without its GRU) on ``run_dir``'s aggregate, score it on the held-out
    episodes and drive it on ``episodes`` validation episodes; the row (module docstring). ``overrides``: the
    run's ``agent.*`` fields changed as ``dagger_forms --set`` changes them (the encoder's and the head's sizes)."""
    import torch as th

    from agents.recurrent import RecurrentForm, RecurrentStudent, save_student
    from train.dagger_forms import student_config

    cfg = student_config(run_dir, list(overrides or []))
    agent = cfg["agent"]
    data = load_episodes(run_dir)
    fitted, held = split_episodes(data, holdout, seed)
    th.manual_seed(seed)
    form = RecurrentForm.of_observations(data.obs, attention_dim=int(agent["attention_dim"]),
                                         attention_heads=int(agent["attention_heads"]), hidden=int(hidden),
                                         net_arch=tuple(int(w) for w in agent["net_arch"]),
                                         actions=str(agent["actions"]), action_repeat=int(agent["action_repeat"]),
                                         go_threshold=float(agent["go_threshold"]))
    student = RecurrentStudent(form)
    curve = fit(student, fitted, held, epochs, batch_episodes, float(agent["fit_lr"]), lr_end, seed)
    row = {"run": str(run_dir), "form": "gru" if hidden else "feed-forward", "hidden": hidden, "seed": seed,
           "set": list(overrides or []),
           "parameters": sum(p.numel() for p in student.parameters()), "labels": int(len(data.labels)),
           "episodes_fitted": int(len(fitted.index)), "epochs": epochs, "lr_end": lr_end,
           "fit_accuracy": curve[-1]["fit"], "fit_cpu_s": round(sum(c["fit_cpu_s"] for c in curve), 1),
           "curve": curve}
    if held is not None:
        row.update(holdout=holdout, held_labels=int(held.valid.sum()), held_accuracy=curve[-1]["held"])
    if save is not None:
        save_student(student, save, extra={"run": str(run_dir), "held_accuracy": row.get("held_accuracy")})
    if episodes > 0:
        t0 = time.process_time()
        row["val_collision"], row["val_success"] = drive(student, cfg, episodes)
        row.update(val_episodes=episodes, val_cpu_s=round(time.process_time() - t0, 1))
    return row


def drive(student, cfg: dict, episodes: int) -> tuple[float, float]:
    """Validation (collision, success) of ``student`` on ``episodes`` validation episodes on the batch."""
    from agents.recurrent import RecurrentPolicy
    from conf.commands import TrainOptions
    from train.dagger import _validation

    plain = [cfg["env"], cfg["sensors"], cfg["shield"]]
    validation = _validation(TrainOptions(eval_n=episodes), plain, student.form.action_repeat,
                             student.form.actions, True, policy_of=RecurrentPolicy)
    return validation(student)


def main(argv: list[str] | None = None) -> None:
    import torch

    from train.checkpoint import write_text_atomic

    torch.set_num_threads(1)
    parser = ToolParser(prog="python -m train.dagger_recurrent", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="checkpoints/<run_name>/ of a DAgger run (its latest.zip and config.yaml)")
    parser.add_argument("--set", nargs="*", default=[], help="agent.<field>=<value> overrides of the encoder and "
                        "head (agent.attention_dim, agent.attention_heads, agent.net_arch), as dagger_forms --set")
    parser.add_argument("--hidden", type=int, default=64, help="the GRU's state size; 0: no GRU (the control)")
    parser.add_argument("--epochs", type=int, default=12, help="passes over the fitted episodes")
    parser.add_argument("--lr-end", type=float, default=1e-5, help="the step at the last epoch (cosine from fit_lr)")
    parser.add_argument("--holdout", type=float, default=0.1, help="share of episodes kept out and scored (0: none)")
    parser.add_argument("--batch-episodes", type=int, default=10, help="episodes per Adam step")
    parser.add_argument("--episodes", type=int, default=300, help="validation episodes (the split's first); 0: none")
    parser.add_argument("--seed", type=int, default=1, help="initial weights, episode order and the held-out draw")
    parser.add_argument("--out", default=None, help="write the row as JSON here (a file that exists is refused)")
    parser.add_argument("--save", default=None, help="save the fitted student here (a file that exists is refused)")
    args = parser.parse_args(argv)
    if args.hidden < 0 or args.epochs < 1 or args.batch_episodes < 1 or args.episodes < 0 or args.lr_end <= 0 \
            or not 0 <= args.holdout < 1:
        parser.error(f"--hidden must be >= 0, --epochs and --batch-episodes >= 1, --episodes >= 0, --lr-end > 0, "
                     f"--holdout in [0, 1); got {args.hidden}, {args.epochs}, {args.batch_episodes}, "
                     f"{args.episodes}, {args.lr_end}, {args.holdout}")
    for name in ("out", "save"):
        if getattr(args, name) and Path(getattr(args, name)).exists():
            parser.error(f"--{name} {getattr(args, name)} exists: another fit's; choose another file")
    row = screen(Path(args.run_dir), args.hidden, args.epochs, args.lr_end, args.holdout, args.episodes, args.seed,
                 args.batch_episodes, Path(args.save) if args.save else None, list(args.set))
    print(json.dumps({k: v for k, v in row.items() if k != "curve"}))
    if args.out:
        write_text_atomic(Path(args.out), json.dumps(row, indent=1) + "\n")


if __name__ == "__main__":
    run_cli(main)
