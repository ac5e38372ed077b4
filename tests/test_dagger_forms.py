"""DAgger's student forms: the disagreement weights (agent.disagree_weight) weigh the states
where the student chooses otherwise than its teacher, the weighted fit moves the student towards those labels, one
config value reaches the round's refit, and the offline screen (train/dagger_forms.py) refuses what it cannot
build in one line."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from train.dagger import Round


@pytest.fixture(autouse=True)
def _one_torch_thread():
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


class _Env(gym.Env):
    """A Dict observation and two choices: enough for an SB3 MultiInputPolicy (never stepped)."""

    observation_space = gym.spaces.Dict({"x": gym.spaces.Box(-1.0, 1.0, (3,), np.float32)})
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        return {"x": np.zeros(3, np.float32)}, {}

    def step(self, action):
        return {"x": np.zeros(3, np.float32)}, 0.0, True, False, {}


def _model(action_space=None, seed: int = 0):
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    class Env(_Env):
        pass

    if action_space is not None:
        Env.action_space = action_space
    return PPO("MultiInputPolicy", DummyVecEnv([Env]), seed=seed, device="cpu", verbose=0,
               policy_kwargs={"net_arch": [16]})


def _choices(model, x: np.ndarray) -> np.ndarray:
    import torch as th

    with th.no_grad():
        obs = model.policy.obs_to_tensor({"x": x})[0]
        return model.policy.get_distribution(obs).distribution.probs.argmax(1).numpy()


def test_the_weights_are_larger_exactly_where_the_student_disagrees_with_the_teacher():
    """Labels equal to the student's own choice on even states and the other choice on odd ones: weight w on the
    odd states, 1 on the even, whatever the student's choices are."""
    from train.dagger import disagreement_weights

    model = _model()
    x = np.random.default_rng(3).uniform(-1, 1, (400, 3)).astype(np.float32)
    own = _choices(model, x)
    labels = np.where(np.arange(400) % 2 == 0, own, 1 - own)
    data = Round(obs=[{"x": row} for row in x], labels=list(labels))
    w = disagreement_weights(model, data, 4.0, chunk=64)  # chunks smaller than the aggregate: their seams too
    assert w.shape == (400,)
    np.testing.assert_array_equal(w, np.where(np.arange(400) % 2 == 1, 4.0, 1.0))


def test_a_continuous_student_has_no_choice_to_disagree_on_and_says_so():
    from av_gym.errors import ConfigError
    from train.dagger import disagreement_weights

    model = _model(gym.spaces.Box(-1.0, 1.0, (1,), np.float32))
    data = Round(obs=[{"x": np.zeros(3, np.float32)}], labels=[np.zeros(1)])
    with pytest.raises(ConfigError, match="agent.disagree_weight=2 needs discrete choices"):
        disagreement_weights(model, data, 2.0)


def test_the_weighted_fit_leans_towards_the_heavier_labels():
    """One observation labelled 0 on 60 states and 1 on 60: the plain fit's P(1) is ~0.5, the fit that weighs the
    1-labels 3 times ~0.75 (the weighted share); the weights must reach the actor's loss to get there."""
    from train.imitation import Demonstrations, fit_policy

    x = np.full(3, 0.3, np.float32)
    labels = [0] * 60 + [1] * 60
    p_one = []
    for weights in (None, np.array([1.0] * 60 + [3.0] * 60)):
        model = _model(seed=5)
        demos = Demonstrations(0.0, [{"x": x}] * 120, labels, [0.0] * 120)
        fit_policy(model.policy, demos, True, 60, 40, 3e-3, seed=1, weights=weights)
        import torch as th

        with th.no_grad():
            obs = model.policy.obs_to_tensor({"x": x[None]})[0]
            p_one.append(float(model.policy.get_distribution(obs).distribution.probs[0, 1]))
    assert abs(p_one[0] - 0.5) < 0.05, p_one
    assert abs(p_one[1] - 0.75) < 0.05, p_one


def test_agent_disagree_weight_is_what_the_rounds_refit_uses(monkeypatch):
    """The round reads agent.disagree_weight once and hands it to the refit; 1 (the default) fits unweighted."""
    import train.dagger as dagger
    from agents.dagger import DaggerParams

    seen = []

    def fake_fit(model, data, epochs, batch, lr, seed, disagree_weight=1.0):
        seen.append(disagree_weight)
        return 1.0

    monkeypatch.setattr(dagger, "fit", fake_fit)
    new = Round(obs=[{"x": np.zeros(3)}], labels=[0], returns=[0.0], agree=[1.0], outcomes=[(0.0, 1.0)])
    run = dagger._Run(model=None, stacks=[], drive=lambda seeds, by_teacher: new, how="batched", validation=None)
    for weight in (1.0, 2.5):
        params = DaggerParams(rounds=2, round_episodes=1, disagree_weight=weight)
        dagger._round(run, params, Round(), 1, 600_000, 1, 0.0, lambda m, on: None)
    assert seen == [1.0, 2.5]
    monkeypatch.undo()  # the real refit, down to the weights it hands the fit
    captured = []
    monkeypatch.setattr("train.imitation.fit_policy", lambda *a, **k: captured.append(k["weights"]) or 1.0)
    model = _model()
    data = Round(obs=[{"x": np.zeros(3, np.float32)}] * 4, labels=[0, 1, 0, 1], returns=[0.0] * 4)
    dagger.fit(model, data, 1, 2, 1e-3, 0)
    dagger.fit(model, data, 1, 2, 1e-3, 0, 3.0)
    assert captured[0] is None
    assert sorted(set(captured[1])) == [1.0, 3.0]  # the labels 0 and 1 on one state: the student gets one wrong


def test_disagree_weight_is_bounded_and_refused_for_continuous_actions():
    from av_gym.errors import ConfigError
    from agents.dagger import DaggerParams

    assert DaggerParams.from_mapping({"disagree_weight": 2.0}, where="agent").disagree_weight == 2.0
    for bad in (0.5, 1000.0):
        with pytest.raises(ConfigError, match="disagree_weight"):
            DaggerParams.from_mapping({"disagree_weight": bad}, where="agent")


@pytest.mark.slow  # the figure script run twice as a process: ~15 s alone at load 2.3
def test_a_second_training_seed_extends_the_curve_and_keeps_its_record(tmp_path):
    """--extend: the curve's rows stay as they were, the new run's validated rounds go before the planner's row;
    a run the curve already holds is refused in one line and the file is left as it was."""
    import csv
    import shutil

    from test_dagger_curve import HEADER, _run

    first = tmp_path / "checkpoints" / "dagger_curve_s1"
    first.mkdir(parents=True)
    (first / "rounds.csv").write_text(HEADER + "0,teacher,10,300,1,1,0.5,0.9,0,0.9,0.5,0.2\n")
    (tmp_path / "planner.csv").write_text("agent,episode,collision,success,split\n" + "".join(
        f"belief_lookahead,{i},0.0,1.0,validation\n" for i in range(10)))
    made = _run("checkpoints/dagger_curve_s1/rounds.csv", "--planner", "planner.csv", "--curve", "curve.csv", "--out",
                "a.png", cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    before = (tmp_path / "curve.csv").read_text()
    second = tmp_path / "checkpoints" / "dagger_curve_s2"
    shutil.copytree(first, second)
    (second / "rounds.csv").write_text(HEADER + "0,teacher,10,310,1,1,0.5,0.9,0,0.9,0.4,0.1\n"
                                                "1,student,15,720,2,1,0.6,0.7,0.1,0.9,nan,nan\n")
    res = _run("checkpoints/dagger_curve_s2/rounds.csv", "--curve", "curve.csv", "--extend", "--out", "b.png",
               cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    after = (tmp_path / "curve.csv").read_text()
    got = list(csv.DictReader(open(tmp_path / "curve.csv")))
    assert [(r["series"], r["run"], r["labels"]) for r in got] == [
        ("student", "dagger_curve_s1", "300"), ("student", "dagger_curve_s2", "310"),
        ("planner", "belief_lookahead", "")]
    assert after.splitlines()[:2] == before.splitlines()[:2] and after.splitlines()[-1] == before.splitlines()[-1]
    again = _run("checkpoints/dagger_curve_s2/rounds.csv", "--curve", "curve.csv", "--extend", "--out", "c.png",
                 cwd=tmp_path)
    lines = [line for line in again.stderr.splitlines() if line.strip()]
    assert again.returncode == 2 and len(lines) == 1 and "that curve.csv does not hold" in lines[0], again.stderr
    assert (tmp_path / "curve.csv").read_text() == after and not (tmp_path / "c.png").exists()


def test_a_steering_student_with_disagreement_weights_is_refused_before_any_folder():
    from test_dagger import _cfg

    from train.dagger import validate

    lane = ("agent=dagger_turn", "env=lane_keeping", "sensors=truth", "agent.actions=env", "agent.teacher=pid_tuned",
            "agent.vec_env=dummy", "agent.extractor=mlp", "agent.action_repeat=1")
    assert validate(_cfg(*lane)) == []
    (line,) = validate(_cfg(*lane, "agent.disagree_weight=2"))
    assert line == ("agent.disagree_weight=2 needs discrete choices to disagree on (agent.actions=go_yield or "
                    "env.action=discrete); got agent.actions=env on env=lane_keeping"), line
    assert validate(_cfg("agent=dagger_turn_memory", "agent.disagree_weight=2")) == []


def test_the_screen_fits_a_form_on_a_runs_aggregate_and_refuses_what_it_cannot_build(tmp_path, capsys):
    """A tiny DAgger run (one round, the batched oracle), then ``python -m train.dagger_forms`` on it: the row
    counts the run's labels and the form's own parameters (another head: another count), a bad --set and an --out
    that exists are one line each and write nothing."""
    import json

    from omegaconf import OmegaConf
    from test_dagger import _cfg

    from av_gym.errors import ConfigError
    from train.dagger import train_dagger
    from train.dagger_forms import main

    cfg = _cfg("agent=dagger_turn", "agent.rounds=1", "agent.round_episodes=2", "agent.n_envs=2",
               "agent.fit_epochs=1", "train.eval_n=0", "train.progress_bar=false")
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    (ckpt / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    train_dagger(cfg, ckpt, tmp_path / "run")
    labels = int((ckpt / "rounds.csv").read_text().splitlines()[1].split(",")[3])
    rows = []
    for name, extra in (("plain", []), ("deep", ["--set", "agent.net_arch=[32,32,32]", "agent.disagree_weight=3"])):
        main([str(ckpt), "--refits", "2", "--epochs", "1", "--episodes", "2", "--out", str(tmp_path / f"{name}.json"),
              *extra])
        rows.append(json.loads((tmp_path / f"{name}.json").read_text()))
    assert [r["labels"] for r in rows] == [labels, labels] and rows[1]["set"][0] == "agent.net_arch=[32,32,32]"
    assert rows[1]["parameters"] != rows[0]["parameters"]
    assert all(0 <= r["val_success"] <= 1 and r["val_episodes"] == 2 for r in rows)
    # half the run's 2 episodes held out of a fit on a falling step, no drive: the held-out states are scored
    # after every epoch and are not fitted (their count and the fitted ones' make the run's labels)
    main([str(ckpt), "--refits", "1", "--epochs", "3", "--episodes", "0", "--holdout", "0.5", "--lr-end", "1e-5",
          "--out", str(tmp_path / "held.json")])
    held = json.loads((tmp_path / "held.json").read_text())
    lr0 = float(cfg.agent.fit_lr)
    assert 0 < held["held_labels"] < labels and "val_success" not in held
    assert [c["lr"] for c in held["curve"]] == pytest.approx([lr0, 0.5 * (lr0 + 1e-5), 1e-5])
    assert held["held_accuracy"] == held["curve"][-1]["held"] and 0 <= held["held_accuracy"] <= 1
    # the observation's ceiling on the same aggregate: its 2 episodes found from the elapsed time, every state read
    from train.observation_ceiling import main as ceiling_main

    ceiling_main([str(ckpt), "--queries", "5", "--k", "1", "--out", str(tmp_path / "ceiling.json")])
    ceiling = json.loads((tmp_path / "ceiling.json").read_text())
    assert ceiling["states"] == labels and ceiling["episodes"] == 2 and ceiling["neighbours"]["queries"] == 5
    for bad, needle in ((["--set", "agent.no_such_field=1"], "--set takes agent.<field>=<value>"),
                        (["--set", "agent.disagree_weight=0.5"], "disagree_weight")):
        with pytest.raises(ConfigError, match=needle):
            main([str(ckpt), "--out", str(tmp_path / "bad.json"), *bad])
    with pytest.raises(SystemExit) as stop:
        main([str(ckpt), "--out", str(tmp_path / "plain.json")])
    assert stop.value.code == 2 and "--out" in capsys.readouterr().err
    assert not (tmp_path / "bad.json").exists()
