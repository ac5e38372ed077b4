"""DAgger for the perceived student on the batch (``agent=dagger_turn_perceived agent.vec_env=batched``).

The batch runs the detector and the tracker (av_gym/batched/perception.py) and the look-ahead oracle labels its rows
directly (train/dagger.py :func:`~train.dagger.drive_batched`). The reference recipe drove the same episodes on
per-env stacks while the oracle labelled a batched replica (:func:`~train.dagger.drive_replica`). A round on the
batch must be that round: the same states seen, the same labels, the same episodes' outcomes, so that students
trained either way differ only by the order of their fits, not by what they were taught."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from tests.test_dagger import _cfg, _one_torch_thread  # noqa: F401 (the fixture: one torch thread, as train)

ROOT = Path(__file__).resolve().parent.parent
SEEDS = list(range(650_000, 650_006))  # seed 1's first training episodes (agent.train_seed + 50,000 x seed)


def _oracle_labels_module():
    spec = importlib.util.spec_from_file_location("oracle_labels", ROOT / "benchmarks" / "oracle_labels.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _student():
    """The committed perceived student (saved at P(GO) >= 0.9): a real policy of the tracker's features, so the
    episodes go through yielding, waiting and going as in training."""
    from agents.checkpoint import load_sb3

    return load_sb3(ROOT / "checkpoints/reference/dagger_turn_perceived/model.zip", device="cpu")


def _batch_round(B: int, teacher_drives: bool):
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from train.dagger import BatchedLabels, drive_batched

    cfg = _cfg("agent=dagger_turn_perceived", "agent.vec_env=batched")
    plain = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
    venv = BatchedLeftTurnVecEnv(*plain, B, action_repeat=5, actions="go_yield", timeout_is_terminal=True, pool=0)
    return drive_batched(venv, _student(), BatchedLabels(venv, None, True, 0.0), SEEDS, teacher_drives, 0.95)


def _replica_round(B: int, teacher_drives: bool):
    from train.dagger import drive_replica

    envs, replica, labeller = _oracle_labels_module().replica_stack(B)
    try:
        return drive_replica(envs, replica, _student(), labeller, SEEDS, teacher_drives, 0.95)
    finally:
        for e in envs:
            e.close()


def test_the_batch_picks_its_own_oracle_for_the_perceived_student():
    """``agent.vec_env=batched`` with turn_perceived: the oracle labels the batch itself (no replica, no per-env
    stack) and the config passes DAgger's checks; the per-env default keeps its replica."""
    from train.dagger import labeller_of, validate

    cfg = _cfg("agent=dagger_turn_perceived", "agent.vec_env=batched", "agent.n_envs=64")
    assert validate(cfg) == []
    assert labeller_of(cfg) == "batched"
    assert labeller_of(_cfg("agent=dagger_turn_perceived")) == "replica"


@pytest.mark.slow  # six episodes on the batch and on per-env tracker stacks: ~12 s alone at load 2.3
@pytest.mark.parametrize("teacher_drives", [False, True],
                         ids=["student_drives", "teacher_drives"])  # the student drives from round 0 (init_from)
def test_a_round_on_the_batch_is_the_replica_recipes_round(teacher_drives):
    """Six training episodes, the same rows: every decision's label, the student's agreement, the discounted returns
    and each episode's outcome equal to the reference recipe's, the returns to float32's precision (the batch's
    rewards) (per-env tracker stacks + the oracle on a replica);
    the observations equal to the tracker's tolerance (the batch's features within 1e-4 of the per-env ones,
    tests/test_batched_perception.py). A label drawn from anything but the simulator's state (the detector's
    generator disturbed by the oracle's futures, a track read as a vehicle) changes a label or an outcome."""
    batch, ref = _batch_round(3, teacher_drives), _replica_round(3, teacher_drives)
    assert len(ref.labels) >= 60 and 0 < int(np.sum(ref.labels)) < len(ref.labels)  # both labels occur
    assert batch.labels == ref.labels
    assert batch.agree == ref.agree
    assert batch.outcomes == ref.outcomes and len(ref.outcomes) == len(SEEDS)
    assert np.allclose(batch.returns, ref.returns, rtol=1e-6, atol=0)  # the batch's rewards are float32
    assert set(batch.obs[0]) == set(ref.obs[0])
    for mine, theirs in zip(batch.obs, ref.obs):
        for k in theirs:
            assert np.allclose(mine[k], theirs[k], rtol=0, atol=1e-4), k


def _round_of_a_run(*overrides: str):
    """Round 0 of a DAgger run on the batch's perceived stack (6 training episodes, 3 envs), as ``python -m train``
    builds it (:func:`train.dagger._build`): the student from init_from, the committed perceived student (saved at
    P(GO) >= 0.9)."""
    from agents.dagger import DaggerParams
    from conf.commands import TrainCommand
    from train.dagger import Round, _build, _operating_point, _round, round_seeds

    cfg = _cfg("agent=dagger_turn_perceived", "agent.vec_env=batched", "agent.n_envs=3", "agent.fit_epochs=1",
               "agent.rounds=1", f"agent.round_episodes={len(SEEDS)}", "train.eval_n=0",
               "agent.init_from=checkpoints/reference/dagger_turn_perceived", "seed=1", *overrides)
    params = DaggerParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
    command = TrainCommand.of(cfg)
    assert command.seed == 1 and round_seeds(params, params.train_seed + 50_000, 0) == SEEDS
    run = _build(cfg, command, params, resume=False)
    try:
        return _round(run, params, Round(), 0, params.train_seed + 50_000, 1, 0.0, _operating_point(params))[1]
    finally:
        for e in run.stacks:
            e.close()


@pytest.mark.slow  # rounds driven on the batch with the tracker: ~11 s alone at load 2.3
def test_drive_at_threshold_labels_the_states_the_student_meets_at_its_operating_point():
    """agent.drive_at_threshold: the rounds are driven at go_threshold (0.9) of the student's fit, from round 0 (the
    init, saved at its own 0.9, moved back to its fit's boundary first), so its labelled states and outcomes are
    those of the committed student driven as shipped; the default drives the init as loaded (its argmax), and a
    round driven at 0.9 on top of the saved 0.9 (P(GO) >= 0.988) yields where the shipped student goes."""
    from agents.batched_vec_env import BatchedLeftTurnVecEnv
    from train.dagger import BatchedLabels, drive_batched

    at_tau, default = _round_of_a_run("agent.drive_at_threshold=true"), _round_of_a_run()
    cfg = _cfg("agent=dagger_turn_perceived", "agent.vec_env=batched")
    plain = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
    venv = BatchedLeftTurnVecEnv(*plain, 3, action_repeat=5, actions="go_yield", timeout_is_terminal=True, pool=0)
    shipped = drive_batched(venv, _student(), BatchedLabels(venv, None, True, 0.0), SEEDS, False, 0.95)
    assert len(shipped.labels) >= 60 and 0 < sum(shipped.labels) < len(shipped.labels)
    assert at_tau.labels == shipped.labels and at_tau.outcomes == shipped.outcomes
    assert at_tau.agree == shipped.agree
    assert default.labels == shipped.labels  # loaded as saved: the reference recipe's round (test above)


def test_drive_at_threshold_needs_a_go_yield_student():
    from agents.dagger import DaggerParams
    from av_gym.errors import ConfigError

    with pytest.raises(ConfigError, match="drive_at_threshold needs a GO/YIELD student"):
        DaggerParams.from_mapping({"kind": "dagger", "actions": "env", "drive_at_threshold": True}, where="agent")


@pytest.mark.parametrize("folder", ["dagger_turn_perceived_batch", *(f"seeds/dagger_turn_perceived_batch/s{s}"
                                                                       for s in (2, 3, 4, 5))])
def test_the_batch_preset_is_the_recipe_of_its_shipped_students(folder):
    """``agent=dagger_turn_perceived_batch`` composes the env, sensors and agent sections each shipped seed was
    trained with (its config.yaml), every field but the operating point, which each seed's go_threshold records
    (chosen on 1,000 validation episodes after training; the preset keeps the training runs' 0.9): a preset that
    drifts from the recipe (init_from, the rounds, the batch, the sensors) would name a method it does not train."""
    import yaml

    saved = yaml.safe_load((ROOT / "checkpoints" / "reference" / folder / "config.yaml").read_text())
    cfg = _cfg("agent=dagger_turn_perceived_batch", f"seed={saved['seed']}")
    composed = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("env", "sensors", "agent")}
    assert saved["agent"]["go_threshold"] in (0.8, 0.9, 0.95) and composed["agent"]["go_threshold"] == 0.9
    saved["agent"]["go_threshold"] = composed["agent"]["go_threshold"]
    # agent.workers says where the labels are made (one process's aggregate in any case), not what is trained;
    # the shipped seeds' config.yaml predate it, and ran in one process
    assert composed["agent"].pop("workers") == saved["agent"].pop("workers", 1) == 1
    for section in composed:
        assert composed[section] == saved[section], section
    assert saved["agent"]["init_from"] is None and saved["agent"]["vec_env"] == "batched"
