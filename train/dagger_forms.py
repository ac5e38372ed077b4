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


def screen(run_dir: Path, overrides: list[str], refits: int, epochs: int, episodes: int, seed: int) -> dict:
    """Fit the form ``overrides`` on ``run_dir``'s aggregate and validate it; the row (labels, fit accuracy,
    validation collision and success, process CPU seconds of the fit and of the validation)."""
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from agents.ppo import make_ppo
    from conf.commands import TrainOptions
    from train.dagger import STATE_MEMBER, _operating_point, _validation, fit, unpack_rounds

    cfg = student_config(run_dir, overrides)
    agent, plain = cfg["agent"], [cfg["env"], cfg["sensors"], cfg["shield"]]
    data = _aggregate(run_dir / "latest.zip", STATE_MEMBER, unpack_rounds)
    repeat, actions = int(agent["action_repeat"]), str(agent["actions"])
    env = BatchedLeftTurnVecEnv(*plain, 2, action_repeat=repeat, actions=actions,
                                timeout_is_terminal=bool(agent["timeout_is_terminal"]), pool=0)
    model = make_ppo(env, agent, seed=seed, tensorboard_log=None, device="cpu")
    env.close()
    t0 = time.process_time()
    for k in range(refits):
        accuracy = fit(model, data, epochs, int(agent["fit_batch"]), float(agent["fit_lr"]), seed * 1000 + k,
                       float(agent.get("disagree_weight", 1.0)))
    t1 = time.process_time()
    from agents.dagger import DaggerParams

    _operating_point(DaggerParams.from_mapping(agent, where="agent"))(model, True)
    validation = _validation(TrainOptions(eval_n=episodes), plain, repeat, actions, True)
    collision, success = validation(model)
    return {"run": str(run_dir), "set": overrides, "labels": len(data.labels), "refits": refits, "epochs": epochs,
            "seed": seed, "parameters": sum(p.numel() for p in model.policy.parameters()),
            "fit_accuracy": round(accuracy, 4), "val_episodes": episodes, "val_collision": collision,
            "val_success": success, "fit_cpu_s": round(t1 - t0, 1), "val_cpu_s": round(time.process_time() - t1, 1)}


def _aggregate(latest: Path, member: str, unpack):
    """The labelled states DAgger saved in ``latest`` (one line if it holds none)."""
    import zipfile

    if not latest.is_file():
        raise ConfigError(f"{latest} does not exist: run_dir must be a DAgger run's checkpoint folder")
    with zipfile.ZipFile(latest) as z:
        if member not in z.namelist():
            raise ConfigError(f"{latest} holds no DAgger aggregate ({member}): not a DAgger run's latest.zip")
        return unpack(z.read(member))


def main(argv: list[str] | None = None) -> None:
    import torch

    from train.checkpoint import write_text_atomic

    torch.set_num_threads(1)
    parser = ToolParser(prog="python -m train.dagger_forms", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="checkpoints/<run_name>/ of a DAgger run (its latest.zip and config.yaml)")
    parser.add_argument("--set", nargs="*", default=[], help="agent.<field>=<value> overrides of the student")
    parser.add_argument("--refits", type=int, default=3, help="fits from scratch on the whole aggregate")
    parser.add_argument("--epochs", type=int, default=8, help="epochs per refit")
    parser.add_argument("--episodes", type=int, default=200, help="validation episodes (the split's first)")
    parser.add_argument("--seed", type=int, default=1, help="the student's initial weights and minibatch order")
    parser.add_argument("--out", default=None, help="write the row as JSON here (a file that exists is refused)")
    args = parser.parse_args(argv)
    for name in ("refits", "epochs", "episodes"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if args.out and Path(args.out).exists():
        parser.error(f"--out {args.out} exists: another screen's row; choose another file")
    row = screen(Path(args.run_dir), list(args.set), args.refits, args.epochs, args.episodes, args.seed)
    print(json.dumps(row))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.out), json.dumps(row, indent=1) + "\n")


if __name__ == "__main__":
    run_cli(main)
