"""The batched look-ahead oracle (agents/batched_oracle.py) and DAgger (train/dagger.py).

The oracle's promise is that a row's GO future *is* what happens when that env goes: checked by labelling, then
driving GO on the real engine. Agreement with the per-env oracle on the same states is checked on a few decisions
here and on 200+ under -m slow (benchmarks/oracle_labels.py measures it on 2,000+). DAgger: the loop runs end to end
into a checkpoint ``python -m eval``'s loader drives, and the student's agreement with its teacher on its own states
rises over the rounds on fixed seeds."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from omegaconf import OmegaConf

from agents.batched_oracle import go_futures
from agents.batched_vec_env import BatchedLeftTurnVecEnv
from av_gym.batched.vec_env import meta_actions
from av_gym.batched.left_turn import BatchedLeftTurn
from av_gym.make import highway_config
from av_gym.sim.batched import LENGTH, WIDTH
from av_gym.wrappers import GO, YIELD
from conftest import conf

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """As ``python -m train`` (train.torch_threads=1): on 2 shared cores, torch's own threads make a tiny network's
    step 100x slower (measured: 0.24 s per backward pass)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _cfg(*overrides: str):
    from hydra import compose, initialize_config_module

    with initialize_config_module("conf", version_base="1.3"):
        return compose("train", overrides=list(overrides))


def _plain(cfg) -> list:
    return [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]


def test_go_future_is_what_happens_when_the_env_goes():
    """Label 12 envs after 1-3 s of yielding, then let the real engine GO: each row's collision and end time are the
    future's, and labelling left the engine as it was (its next observation unchanged)."""
    _, config = highway_config(conf("env", "left_turn"))
    eng = BatchedLeftTurn(12, config)
    eng.reset(list(range(3200, 3212)))
    rng = np.random.default_rng(0)
    wait = rng.integers(10, 30, 12)  # env steps each row yields first
    active = np.ones(12, bool)
    for k in range(int(wait.max())):
        turn = eng.observe()
        choice = np.where(k < wait, YIELD, GO)
        _, term, trunc = eng.step(meta_actions(choice, turn), active & (k < wait))
        active &= ~(term | trunc)
    rows = np.nonzero(active)[0]
    before = eng.observe(rows).copy()
    fut = go_futures(eng, rows)
    assert np.array_equal(eng.observe(rows), before)
    live = np.zeros(12, bool)
    live[rows] = True
    crashed, ended = np.zeros(12, bool), np.full(12, np.nan)
    while live.any():
        _, term, trunc = eng.step(meta_actions(np.full(12, GO), eng.observe()), live)
        done = (term | trunc) & live
        d = np.nonzero(done)[0]
        crashed[d] = eng.traffic.crashed[d, eng.ego_slot(d)]
        ended[d] = eng.time[d]
        live &= ~done
    assert len(rows) >= 8
    assert np.array_equal(fut.safe, ~crashed[rows])
    assert np.allclose(fut.end_time, ended[rows])
    assert (~fut.safe).any() and fut.safe.any()  # both labels occur: the check can tell them apart
    assert np.all(fut.min_gap[~fut.safe] < np.hypot(LENGTH, WIDTH))  # touching boxes: centres within a diagonal


def _benchmark():
    spec = importlib.util.spec_from_file_location("oracle_labels", ROOT / "benchmarks" / "oracle_labels.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _agreement(episodes: int) -> tuple[int, int]:
    bench = _benchmark()
    plain = bench.stacks()
    recorded, *_ = bench.per_env(plain, range(7_100_000, 7_100_000 + episodes), 0.25, shortcut=True)
    labels, *_ = bench.batched(plain, recorded, min(episodes, 16))
    n, agree, go, differ = bench.agreement(recorded, labels)
    assert differ == 0 and 0 < go < n  # same episodes on both stacks, both labels present
    return n, agree


def test_batched_oracle_agrees_with_per_env_oracle_on_a_few_decisions():
    n, agree = _agreement(1)
    assert n >= 10 and agree == n


@pytest.mark.slow
def test_batched_oracle_agrees_with_per_env_oracle_on_200_decisions():
    n, agree = _agreement(12)
    assert n >= 200 and agree == n


@pytest.mark.slow  # trains (a subprocess / several rounds): over the README test budget
def test_dagger_runs_end_to_end_into_an_evaluable_checkpoint(tmp_path):
    """A tiny DAgger run (2 rounds of 2 episodes, the batched oracle): rounds.csv, TensorBoard events, an atomic
    latest.zip, best.zip (validation ran), and model.zip that the evaluation's loader drives."""
    from av_gym.make import make_env
    from eval.agents import _load_trained
    from train.dagger import train_dagger

    cfg = _cfg("agent=dagger_turn", "agent.rounds=2", "agent.round_episodes=2", "agent.n_envs=2",
               "agent.extractor=mlp", "agent.fit_epochs=1", "train.eval_n=2", "train.progress_bar=false")
    ckpt, run = tmp_path / "ckpt", tmp_path / "run"
    ckpt.mkdir()
    (ckpt / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    path = train_dagger(cfg, ckpt, run)
    rounds = (ckpt / "rounds.csv").read_text().splitlines()
    assert rounds[0].startswith("round,driver") and len(rounds) == 3
    assert rounds[1].split(",")[1] == "teacher" and rounds[2].split(",")[1] == "student"
    assert {p.name for p in ckpt.glob("*.zip")} == {"latest.zip", "best.zip", "model.zip"}
    assert list((run / "tb" / "dagger_turn").glob("events.out.tfevents.*"))
    env = make_env(*_plain(cfg))
    policy = _load_trained(path.parent, env, "left_turn")
    obs, _ = env.reset(seed=5)
    for _ in range(20):
        obs, _, term, trunc, _ = env.step(policy.act(obs))
        if term or trunc:
            break
    env.close()


def _after_3s(env, obs, info) -> int:
    """A toy teacher a small network can match: YIELD for the first 3 s of the episode, then GO."""
    return GO if 20.0 * float(obs["turn"][4]) >= 3.0 else YIELD


@pytest.mark.slow  # trains (a subprocess / several rounds): over the README test budget
def test_student_agreement_with_its_teacher_rises_over_rounds():
    """DAgger's loop (drive, label the driven states, aggregate, refit) with a toy teacher: on 4 fixed seeds the
    student drives and the teacher labels its states, before the rounds and after each; the agreement rises from
    the untrained student's and ends near 1 (labels attached to the wrong states, or a fit that does not see the
    aggregate, keep it down)."""
    from agents.ppo import make_ppo
    from train.dagger import BatchedLabels, Round, aggregate, drive_batched, fit

    cfg = _cfg("agent=dagger_turn", "agent.extractor=mlp")
    venv = BatchedLeftTurnVecEnv(*_plain(cfg), 4, action_repeat=5, actions="go_yield", timeout_is_terminal=True, pool=0)
    model = make_ppo(venv, OmegaConf.to_container(cfg.agent, resolve=True), seed=0, tensorboard_log=None)
    labels = BatchedLabels(venv, _after_3s, False, 0.0)
    fixed = range(9_900_000, 9_900_004)

    def agreement() -> float:
        return float(np.mean(drive_batched(venv, model, labels, fixed, False, 0.95).agree))

    data, seen = Round(), [agreement()]
    for k in range(3):
        aggregate(data, drive_batched(venv, model, labels, range(9_800_000 + 4 * k, 9_800_004 + 4 * k), k == 0,
                                      0.95))
        fit(model, data, 60, 16, 3e-3, k)
        seen.append(agreement())
    assert seen[-1] > seen[0] + 0.1 and seen[-1] >= 0.9, seen


def test_go_threshold_moves_the_decision_boundary():
    """train/operating_point.py: after shift_go(τ) the student GOes exactly where its unshifted P(GO) >= τ."""
    import torch as th

    from agents.ppo import make_ppo
    from train.operating_point import shift_go

    cfg = _cfg("agent=dagger_turn", "agent.extractor=mlp")
    venv = BatchedLeftTurnVecEnv(*_plain(cfg), 16, action_repeat=5, actions="go_yield", pool=0)
    model = make_ppo(venv, OmegaConf.to_container(cfg.agent, resolve=True), seed=0, tensorboard_log=None)
    with th.no_grad():  # spread the untrained logits so that P(GO) covers (0, 1)
        model.policy.action_net.weight.mul_(40.0)
    obs = venv.reset()
    with th.no_grad():
        p_go = model.policy.get_distribution(model.policy.obs_to_tensor(obs)[0]).distribution.probs[:, GO].numpy()
    tau = float(np.mean(np.sort(p_go)[7:9]))  # between two students' P(GO): no tie at the boundary
    shift_go(model, tau)
    choice = model.predict(obs, deterministic=True)[0]
    assert 0 < (choice == GO).sum() < len(choice)
    assert np.array_equal(choice == GO, p_go >= tau)


@pytest.mark.slow
def test_dagger_on_perceived_features_runs_on_the_per_env_stack(tmp_path):
    """Any student observation: turn_perceived (detector + tracker) needs the per-env stack, where the per-env oracle
    labels one state at a time (labeller per_env) or the batched oracle a replica of the episodes (replica, what
    auto picks); the student's observation space is the tracker's features."""
    from train.dagger import labeller_of, train_dagger

    cfg = _cfg("agent=dagger_turn", "sensors=turn_perceived", "agent.vec_env=dummy", "agent.rounds=2",
               "agent.round_episodes=1", "agent.extractor=mlp", "agent.fit_epochs=1", "train.eval_n=1",
               "train.progress_bar=false", "agent.labeller=per_env")
    assert labeller_of(cfg) == "per_env"
    assert labeller_of(_cfg("agent=dagger_turn_perceived")) == "replica"
    path = train_dagger(cfg, tmp_path / "ckpt", tmp_path / "run")
    rows = (tmp_path / "ckpt" / "rounds.csv").read_text().splitlines()
    assert path.is_file() and len(rows) == 3
    # the replica labeller, from the truth student (init_from): the student drives from round 0
    cfg = _cfg("agent=dagger_turn_perceived", "agent.rounds=2", "agent.round_episodes=2", "agent.n_envs=2",
               "agent.fit_epochs=1", "train.eval_n=0", "train.progress_bar=false")
    path = train_dagger(cfg, tmp_path / "ckpt2", tmp_path / "run2")
    rows = (tmp_path / "ckpt2" / "rounds.csv").read_text().splitlines()
    assert path.is_file() and [r.split(",")[1] for r in rows[1:]] == ["student", "student"]


class _Spaces(gym.Env):
    """An env with a checkpoint's spaces, enough for SB3 to build a PPO on them (never stepped)."""

    def __init__(self, observation_space, action_space) -> None:
        self.observation_space, self.action_space = observation_space, action_space


# ppo_turn's rollout is 64 envs x 8 steps; built on this one-env stand-in, SB3 warns that 8 < its mini-batch of 128
@pytest.mark.filterwarnings("ignore:You have specified a mini-batch size:UserWarning")
def test_init_from_starts_ppo_from_the_students_network_and_refuses_a_misfit():
    """``agent.init_from=checkpoints/reference/dagger_turn``: a fresh PPO of ppo_turn's config acts as the DAgger
    student on its own decisions (PPO fine-tuning starts where DAgger ended); a checkpoint of other spaces (the lane
    keeper) and ``init`` + ``init_from`` together are one-line errors naming the field."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.ppo import PPOParams, make_ppo
    from av_gym.errors import ConfigError
    from eval.agents import load_agent_config
    from train.ppo import load_weights

    student = PPO.load("checkpoints/reference/dagger_turn/model.zip", device="cpu")
    venv = DummyVecEnv([lambda: _Spaces(student.observation_space, student.action_space)])
    model = make_ppo(venv, load_agent_config("ppo_turn"), seed=0, tensorboard_log=None)
    rng = np.random.default_rng(3)
    obs = {k: rng.uniform(-1, 1, (64, *space.shape)).astype(space.dtype)
           for k, space in student.observation_space.spaces.items()}
    before = model.predict(obs, deterministic=True)[0]
    load_weights(model, "checkpoints/reference/dagger_turn", "left_turn")
    after, wanted = model.predict(obs, deterministic=True)[0], student.predict(obs, deterministic=True)[0]
    assert (after == wanted).all() and not (before == wanted).all()
    with pytest.raises(ConfigError, match="agent.init_from="):
        load_weights(model, "checkpoints/reference/ppo_lane_localized", "left_turn")
    with pytest.raises(ValueError, match="init_from and init both set"):
        PPOParams(init="gap_acceptance", init_from="checkpoints/reference/dagger_turn")


@pytest.mark.slow  # ~30 s: the per-env oracle it is checked against deep-copies the tracker stack per decision
def test_replica_labels_are_the_per_env_oracles_on_perceived_states():
    """``labeller=replica``: the student drives the per-env stack with the detector and tracker; the batched oracle
    labels a replica of its episodes. Every label equals the per-env oracle's (a deep copy of that very per-env env
    played with GO to the end): benchmarks/oracle_labels.py --perceived on three episodes."""
    n, agree, go, *_ = _benchmark().perceived(3, 3, 3_300_000)
    assert n >= 30 and agree == n and 0 < go < n  # both labels occur: the check can tell them apart


def test_a_replica_that_leaves_the_per_env_episode_is_an_error():
    """A replica that is not the per-env episodes (here: a shorter time limit) would label other states: it is
    caught at the first episode that ends differently, not trained on."""
    from train.dagger import drive_replica

    bench = _benchmark()
    envs, replica, labeller = bench.replica_stack(2, ("sensors=turn_truth",), replica_env={"duration": 4.0})
    with pytest.raises(RuntimeError, match="replica left the per-env episode"):
        drive_replica(envs, replica, bench.Coin(1), labeller, list(range(3_300_010, 3_300_016)), True, 0.95)


def test_operating_point_thresholds_are_absolute_for_a_student_saved_at_its_own(tmp_path):
    """checkpoints/reference/dagger_turn was saved at P(GO) >= 0.9 (its config's agent.go_threshold): writing it at
    0.9 gives it back unchanged, at 0.5 moves the GO bias by log(0.9 / 0.1), not by 0 (thresholds stack otherwise)."""
    import math

    from agents.checkpoint import load_sb3
    from train.operating_point import write

    ref = Path("checkpoints/reference/dagger_turn")
    bias = lambda p: float(load_sb3(p, device="cpu").policy.action_net.bias[GO].detach())  # noqa: E731
    same = write(ref, tmp_path / "t0.9", 0.9)
    half = write(ref, tmp_path / "t0.5", 0.5)
    assert bias(same) == pytest.approx(bias(ref / "model.zip"), abs=1e-6)
    assert bias(half) - bias(ref / "model.zip") == pytest.approx(math.log(9.0), abs=1e-5)
    assert "go_threshold: 0.5" in (tmp_path / "t0.5" / "config.yaml").read_text()


def test_auto_labeller_picks_the_replica_only_where_it_can_play_the_episodes():
    """``agent.labeller=auto``: the batched oracle on the batch, its replica for the per-env left turn, the per-env
    teacher where a replica would leave the episode (a shield overrides the per-env car only); asking for the
    replica there is a one-line error naming the field and the reason."""
    from train.dagger import labeller_of, validate

    assert labeller_of(_cfg("agent=dagger_turn")) == "batched"
    assert labeller_of(_cfg("agent=dagger_turn_perceived")) == "replica"
    assert labeller_of(_cfg("agent=dagger_turn_perceived", "shield=aeb")) == "per_env"
    assert labeller_of(_cfg("agent=dagger_turn_perceived", "agent.teacher=gap_acceptance")) == "per_env"
    (problem,) = validate(_cfg("agent=dagger_turn_perceived", "shield=aeb", "agent.labeller=replica"))
    assert problem.startswith("agent.labeller=replica needs") and "shield=aeb" in problem


def test_go_safe_targets_fit_the_probability_not_the_label():
    """agent.targets=go_safe: P(GO) is fitted to the share of the planner's safe futures (cross-entropy to a
    probability), so a state whose futures are safe 70 % of the time ends near 0.7, where its labels alone (GO
    every time) push it to 1."""
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv

    from agents.ppo import make_ppo
    from eval.agents import compose_group
    from train.dagger import Round, fit
    from train.ppo import _env_factory

    sensors = compose_group("sensors", "turn_truth")
    make = lambda: _env_factory(conf("env", "left_turn"), sensors, {"kind": "none"}, 0.0, 5, "go_yield")  # noqa: E731
    space = make().observation_space
    space.seed(3)
    state = space.sample()
    p_go = {}
    for targets in ([], [0.7] * 64):
        model = make_ppo(DummyVecEnv([make]), {"policy": "MultiInputPolicy", "net_arch": [16], "n_steps": 64,
                                               "batch_size": 64}, seed=0, tensorboard_log=None)
        data = Round(obs=[state] * 64, labels=[GO] * 64, returns=[0.0] * 64, targets=targets)
        accuracy = fit(model, data, 40, 16, 3e-3, 1)
        with torch.no_grad():
            probs = model.policy.get_distribution(model.policy.obs_to_tensor(state)[0]).distribution.probs
        p_go[bool(targets)] = float(probs[0, GO])
        assert accuracy == 1.0  # against the labels either way: P(GO) > 0.5
    assert p_go[False] > 0.95 and abs(p_go[True] - 0.7) < 0.05, p_go


def test_go_safe_targets_need_the_belief_planner_on_the_batch():
    from train.dagger import validate

    assert validate(_cfg("agent=dagger_turn_memory", "agent.targets=go_safe")) == []
    (problem,) = validate(_cfg("agent=dagger_turn", "agent.targets=go_safe"))
    assert problem.startswith("agent.targets=go_safe needs agent.teacher of kind belief_lookahead") and \
        "kind lookahead" in problem


def test_growing_rounds_follow_each_other_in_the_train_split():
    """agent.round_growth: round k drives round_episodes x growth^k episodes (rounded), and the rounds' seeds are
    the train split's next ones, so no episode is driven twice (offsets of k x round_episodes overlap once rounds
    grow); growth 1 keeps the equal rounds' seeds, so the shipped students' runs are unchanged."""
    from agents.dagger import DaggerParams
    from av_gym.seeds import train_seed
    from train.dagger import round_seeds

    grown = DaggerParams(rounds=5, round_episodes=10, round_growth=1.5)
    assert grown.round_sizes() == [10, 15, 22, 34, 51]
    seeds = [s for k in range(5) for s in round_seeds(grown, 650_000, k)]
    assert seeds == [train_seed(650_000, i) for i in range(132)]
    equal = DaggerParams(rounds=3, round_episodes=7)
    assert [round_seeds(equal, 650_000, k) for k in range(3)] == \
        [[train_seed(650_000, 7 * k + i) for i in range(7)] for k in range(3)]


def test_growing_rounds_are_bounded_by_the_aggregate_they_hold(tmp_path, monkeypatch, capsys):
    """The bound on the labelled episodes counts the grown rounds (20 x 100 equal rounds fit; grown by 1.5 they
    are 664,852 episodes)."""
    from conf.check import check_command_line
    from tests.test_bad_input import check_line

    assert check_command_line("train", ["agent=dagger_turn", "agent.rounds=20", "agent.round_episodes=100"])
    monkeypatch.chdir(tmp_path)
    line = check_line("train", ["agent=dagger_turn", "agent.rounds=20", "agent.round_episodes=100",
                                "agent.round_growth=1.5"], monkeypatch, capsys)
    assert "agent.rounds x agent.round_episodes must be at most 100,000 episodes" in line and \
        "agent.round_growth=1.5" in line, line
    assert not any(tmp_path.iterdir())


@pytest.mark.slow  # ~3.5 CPU-s (3 rounds of training); the sizes and seeds themselves are checked fast above
def test_a_growing_dagger_run_drives_its_rounds_sizes(tmp_path):
    """End to end (the batched oracle, 3 rounds from 1 episode, x 2 a round): rounds.csv counts 1, 2 and 4
    episodes and the labels grow with them."""
    import csv

    from train.dagger import train_dagger

    cfg = _cfg("agent=dagger_turn", "agent.rounds=3", "agent.round_episodes=1", "agent.round_growth=2",
               "agent.n_envs=2", "agent.extractor=mlp", "agent.fit_epochs=1", "train.eval_n=0",
               "train.progress_bar=false")
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    train_dagger(cfg, ckpt, tmp_path / "run")
    rows = list(csv.DictReader((ckpt / "rounds.csv").open()))
    assert [int(r["episodes"]) for r in rows] == [1, 2, 4]
    labels = [int(r["labels"]) for r in rows]
    assert labels[0] > 0 and labels[1] > labels[0] and labels[2] > labels[1]


def test_the_oracle_drives_its_own_labels_on_the_batch():
    """benchmarks/oracle_labels.py --drive: the teacher drives (round 0's form) with a stand-in student whose
    recorded choices must be actions of the env's space (float zeros were refused by check_actions)."""
    bench = _benchmark()
    collision, success, _ = bench.drive(bench.stacks(), "validation", 4, 4)
    assert 0.0 <= collision <= 1.0 and success > 0.0  # the oracle arrives in ~92 % of episodes
    assert collision + success <= 1.0
