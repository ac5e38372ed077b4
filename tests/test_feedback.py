"""Every long command says what it is doing: a line before each long phase, a bar within it (eval.ccftap's grid,
the figures after ``python -m eval``'s table, the cloning before PPO, ``train.pid_search``), and DAgger's round
lines written past its bar instead of through it. Tested by what is printed and in which order, not by timing."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import numpy as np
from gymnasium import spaces
from tqdm import tqdm

from conf import run_log
from conftest import conf


def test_ccftap_reports_its_runs_as_they_finish(monkeypatch, capsys):
    """It printed one line, then nothing for the grid's 3 minutes. Not on a terminal (here): a line every 5 s."""
    import eval.ccftap as ccftap

    clock = iter([0.0, 4.0, 11.0, 12.0])  # the start, then after each run
    monkeypatch.setattr(run_log.time, "monotonic", lambda: next(clock))
    monkeypatch.setattr(ccftap, "run_case", lambda task: {"case": task["i"]})
    rows = ccftap._run_tasks([{"i": i} for i in range(3)], workers=1)
    assert rows == [{"case": 0}, {"case": 1}, {"case": 2}]
    out = capsys.readouterr()
    assert out.out.splitlines() == ["[ccftap] 2/3 runs, 11 s", "[ccftap] 3/3 runs, 12 s"] and out.err == ""


def test_progress_is_a_bar_on_a_terminal(monkeypatch, capsys):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    assert list(run_log.progress(range(3), 3, "ccftap", "run")) == [0, 1, 2]
    out = capsys.readouterr()
    assert "ccftap: 100%" in out.err and "3/3" in out.err and out.out == ""


def test_pid_search_announces_its_grid_and_shows_a_bar_of_evaluations(monkeypatch, capsys):
    from train import pid_search

    events = []

    class Env:
        def close(self) -> None:
            pass

    def laps(env, gains, seeds):
        events.append("lap")
        return [{"lap_completed": 1.0, "cte_mean_abs_units": gains["kp"], "cte_mean_abs_m": gains["kp"] / 25,
                 "steering_sign_changes_per_100m": 1.0}]

    monkeypatch.setattr(pid_search, "lane_env", lambda track: Env())
    monkeypatch.setattr(pid_search, "run_laps", laps)
    res = pid_search.search(pid_search.GRIDS["quick"], [0], refine=0, margin=0, log=events.append)
    assert events[0].startswith("[pid_search] grid: 4 gain triples x 1 laps on layout A") and events[1] == "lap"
    assert res["evaluations"] == 4
    err = capsys.readouterr().err
    assert "pid_search: 100%" in err and "4/4" in err and "best J 0.850" in err


def test_cloning_announces_each_phase_before_it_runs(monkeypatch):
    """``python -m train`` was silent for its first 21-29 s: the teacher's episodes and the fit."""
    import train.imitation as imitation

    events = []

    def drive(env, model, teacher, seed, student, demos, action_noise, rng):
        events.append("drive")
        demos.add_episode([{"turn": np.zeros(2, np.float32)}], [0], [0.0])
        return (0.0, 1.0)

    def fit(policy, demos, discrete, epochs, batch_size, lr=None, seed=0, desc=None):
        events.append(f"fit {desc}")
        return 1.0

    monkeypatch.setattr(imitation, "_drive", drive)
    monkeypatch.setattr(imitation, "fit_policy", fit)
    env = SimpleNamespace(action_space=spaces.Discrete(2))
    model = SimpleNamespace(policy=None)
    stats = imitation.pretrain_from_teacher(model, env, None, range(3), 0.9, 5, 8, log=events.append, progress=True)
    assert stats["episodes"] == 3
    assert events == ["[train] cloning: the teacher drives 3 demonstration episodes", "drive", "drive", "drive",
                      "[train] cloning: fitting the policy to 3 labelled decisions (5 epochs)", "fit fitting"]


def test_dagger_round_lines_do_not_break_its_bar(capsys):
    """A plain print wrote the round's line straight after the bar's text, on the bar's line."""
    from train.dagger import Round, _print_round

    row = {"round": 0, "driver": "teacher", "episodes": 4, "drive_success": 1.0, "drive_collision": 0.0,
           "agreement": 1.0, "labels": 40, "fit_accuracy": 0.9, "val_success": 0.5, "val_collision": 0.1,
           "wall_s": 3.0}
    new = Round()
    new.labels, new.label_s = [0] * 40, 1.0
    with tqdm(total=2, desc="DAgger rounds", file=sys.stdout, mininterval=0) as bar:
        bar.update()
        _print_round(row, new, True)
        bar.update()
    out = capsys.readouterr().out
    # the bar is cleared (a carriage return and blanks) before the line, which starts a line of its own
    assert any(part.startswith("[train] round 0: teacher drove 4 episodes") for part in out.split("\r"))
    assert "s/it][train] round" not in out and "it/s][train] round" not in out


def test_eval_announces_each_video_before_rendering_it(tmp_path, capsys):
    from av_gym.seeds import config_seeds
    from eval.agents import plan_agent
    from eval.plots import turn_videos

    env = {**conf("env", "left_turn"), "duration": 1.0}
    plans = [plan_agent("always_proceed", "left_turn", conf("sensors", "truth"), {"kind": "none"}, "checkpoints")]
    first = config_seeds("validation", 1, None, "seed").start
    turn_videos(env, plans, tmp_path, first, "checkpoints")
    assert f"[eval] video: always_proceed drives seed {first} once more, rendered into turn_always_proceed.webm" \
        in capsys.readouterr().out


def test_an_episode_in_progress_moves_the_eval_bar(monkeypatch, capsys):
    """The bar advanced once per episode, and a lane-keeping lap takes 10-40 s: now its step count, every second."""
    from eval import runner

    class Env:
        def reset(self, seed=None):
            self.k = 0
            return 0, {}

        def step(self, action):
            self.k += 1
            return 0, 0.0, self.k == 30, False, {"episode_metrics": {"return": 1.0}}

    policy = SimpleNamespace(reset=lambda: None, act=lambda obs: 0)
    clock = iter(np.arange(0.0, 100.0, 0.25))  # a quarter of a second per step
    monkeypatch.setattr(runner.time, "monotonic", lambda: next(clock))
    rows = runner.run_episodes(Env(), policy, [7], "lap", progress=True)
    assert rows == [{"agent": "lap", "episode": 0, "seed": 7, "return": 1.0}]
    err = capsys.readouterr().err
    assert "episode step 4" in err and "episode step 28" in err  # every 4 steps = 1 s
