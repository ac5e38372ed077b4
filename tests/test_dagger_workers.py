"""DAgger's labelling in processes (``agent.workers``, train/dagger.py ``drive_parts``): a round's seeds in
contiguous parts, each driven and labelled on its own batch in a spawned process, merged back into the round one
process gives, the aggregate in the same order (``batch_order``: the order in which one batch ends its episodes);
refused in one line where it cannot run; a run stopped and resumed with two processes ends with the student of an
uninterrupted one-process run."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from av_gym.errors import ConfigError
from train.dagger import Round, batch_order, merge_parts

TIMINGS = ("wall_s", "label_s", "fit_s")


def test_one_batch_ends_its_episodes_by_decision_then_row():
    """Episodes of 3, 1, 2, 2 decisions on 2 rows: row 1 ends episode 1 at decision 1 and takes episode 2 (ends at
    3); at decision 3 row 0 ends episode 0, then row 1 episode 2; row 0 takes episode 3 (ends at 5)."""
    assert batch_order([3, 1, 2, 2], 2) == [1, 0, 2, 3]
    assert batch_order([2, 2, 2], 5) == [0, 1, 2]  # more rows than episodes: all at once, rows in order
    assert batch_order([4, 1, 1, 1], 1) == [0, 1, 2, 3]  # one row: in seed order


def _part(seeds: list[int], lengths: list[int]) -> Round:
    """A part as a labelling process returns it: per decision its seed as the observation and label."""
    out = Round(label_s=1.0)
    for s, n in zip(seeds, lengths):
        out.close([[{"x": np.array([s, i])}, s, 1.0, 0.0] for i in range(n)], {"episode_metrics": {
            "collision": 0.0, "success": float(s % 2)}}, 0.9, seed=s)
    return out


def test_the_parts_merge_into_the_order_of_one_batch_and_a_missing_episode_is_refused():
    seeds, lengths = [10, 11, 12, 13], [3, 1, 2, 2]
    # each part in its own batch's order (part 2 of two rows ends 13 first)
    merged = merge_parts([_part([10, 11], [3, 1]), _part([13, 12], [2, 2])], seeds, width=2)
    assert merged.seeds == [11, 10, 12, 13] and merged.lengths == [1, 3, 2, 2]
    assert merged.labels == [11, 10, 10, 10, 12, 12, 13, 13]
    assert [int(o["x"][1]) for o in merged.obs] == [0, 0, 1, 2, 0, 1, 0, 1]  # each episode's decisions in order
    assert merged.outcomes == [(0.0, 1.0), (0.0, 0.0), (0.0, 0.0), (0.0, 1.0)] and merged.label_s == 2.0
    with pytest.raises(RuntimeError, match="played 2 episodes for the round's 4 seeds"):
        merge_parts([_part([10, 11], [3, 1])], seeds, width=2)


def test_workers_are_refused_off_the_batch_and_below_one():
    from agents.dagger import DaggerParams
    from tests.test_dagger import _cfg
    from train.dagger import validate

    cfg = _cfg("agent=dagger_turn", "agent.vec_env=subproc", "agent.workers=2")
    assert validate(cfg) == ["agent.workers=2 needs agent.vec_env=batched (each labelling process drives its part "
                             "of a round on a batch of its own); got agent.vec_env=subproc: use agent.workers=1"]
    with pytest.raises(ConfigError, match=r"agent\.workers must be an integer in \[1, 64\], got 0"):
        DaggerParams.from_mapping({"workers": 0}, where="agent")


def test_the_parent_of_labelling_processes_builds_only_the_student_it_fits(monkeypatch):
    """With agent.workers=2 the labelling processes drive and label: the parent builds no teacher and no batch of
    agent.n_envs rows (its student's spaces come from one row, a stack the run closes), and hands the processes the
    run's job; with agent.workers=1 it builds the batch it drives and the teacher's labeller."""
    import eval.runner
    import train.imitation
    from agents.dagger import DaggerParams
    from conf.commands import TrainCommand
    from omegaconf import OmegaConf
    from tests.test_dagger import _cfg
    from train.dagger import LabelJob, _build

    teachers: list = []
    make_teacher = train.imitation.make_teacher
    monkeypatch.setattr(train.imitation, "make_teacher", lambda *a: teachers.append(a) or make_teacher(*a))

    class Pool:  # the labelling processes, not started: what the parent hands them
        def __init__(self, n: int, setup, args: tuple) -> None:
            self.n, self.args = n, args

        def close(self, failed: bool) -> None:
            pass
    monkeypatch.setattr(eval.runner, "WorkerPool", Pool)
    for workers in (2, 1):
        cfg = _cfg("agent=dagger_turn", "agent.n_envs=16", f"agent.workers={workers}", "agent.extractor=mlp",
                   "agent.net_arch=[8]", "train.eval_n=0")
        params = DaggerParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
        run = _build(cfg, TrainCommand.of(cfg), params, resume=False)
        if workers == 2:
            assert teachers == [] and [s.num_envs for s in run.stacks] == [1]
            assert run.model.env is run.stacks[0]
            assert run.pool.n == 2 and run.pool.args == (LabelJob.of(cfg, TrainCommand.of(cfg), "batched"),)
        else:
            assert len(teachers) == 1 and run.pool is None and [s.num_envs for s in run.stacks] == [16]
            assert run.model.env is run.stacks[0]


def _tiny(tmp_path: Path, name: str, workers: int) -> tuple:
    """Two rounds of the learning curve's form (the planner's labels, memory features) on 3 rows: 8 episodes, then
    12; the aggregate (latest.zip) and the rounds' rows without their timings."""
    import torch

    from tests.test_dagger import _cfg
    from train.dagger import read_aggregate, train_dagger, unpack_rounds

    cfg = _cfg("agent=dagger_turn_memory", "agent.rounds=2", "agent.round_episodes=8", "agent.round_growth=1.5",
               "agent.n_envs=3", "agent.fit_epochs=1", f"agent.workers={workers}", "train.eval_n=0",
               "train.progress_bar=false")
    ckpt = tmp_path / name
    ckpt.mkdir()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        train_dagger(cfg, ckpt, tmp_path / f"{name}_run")
    finally:
        torch.set_num_threads(threads)
    rows = [{k: v for k, v in r.items() if k not in TIMINGS} for r in csv.DictReader((ckpt / "rounds.csv").open())]
    return read_aggregate(ckpt / "latest.zip", unpack_rounds), rows


@pytest.mark.slow  # two tiny runs of the planner's labels (~1 min on 2 cores)
def test_two_labelling_processes_give_the_aggregate_of_one(tmp_path):
    """The same labelled states in the same order, labels, returns and rounds' rows (agreement, outcomes, fit)
    with the round's seeds in two processes as in one batch: fails if a part is dropped, played twice, or merged
    in another order than one batch's (seed order is not it: 8 episodes on 3 rows end out of order)."""
    one, rows_one = _tiny(tmp_path, "one", 1)
    two, rows_two = _tiny(tmp_path, "two", 2)
    assert rows_two == rows_one and [r["episodes"] for r in rows_one] == ["8", "12"]
    assert len(two.labels) == len(one.labels) > 0
    assert np.array_equal(two.labels, one.labels) and np.array_equal(two.returns, one.returns)
    for a, b in zip(one.obs, two.obs):
        assert all(np.array_equal(a[k], b[k]) for k in a)


@pytest.mark.slow  # three tiny DAgger runs, two of them with two labelling processes
def test_a_run_stopped_and_resumed_in_two_processes_ends_with_the_one_process_student(tmp_path, monkeypatch):
    """As tests/test_nothing_lost.py's resume test, the cut run and its resume labelling in two processes: the
    student bit for bit and the rows (without timings) of the uninterrupted run in one process."""
    import torch

    from agents.checkpoint import load_sb3
    from tests.test_nothing_lost import dagger_run

    whole = dagger_run(tmp_path, "whole")
    with pytest.raises(KeyboardInterrupt):
        dagger_run(tmp_path, "cut", "agent.workers=2", stop_at=2, monkeypatch=monkeypatch)
    resumed = dagger_run(tmp_path, "cut", "agent.workers=2", "train.resume=true")
    a, b = (load_sb3(p, device="cpu").policy.state_dict() for p in (whole, resumed))
    assert all(torch.equal(a[k], b[k]) for k in a), "the same student"

    def rows(path: Path) -> list[dict]:
        return [{k: v for k, v in r.items() if k not in TIMINGS} for r in csv.DictReader(path.open())]
    assert rows(tmp_path / "cut" / "ckpt" / "rounds.csv") == rows(tmp_path / "whole" / "ckpt" / "rounds.csv")
