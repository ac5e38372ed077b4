"""``python -m eval vec_env=batched workers=N``: the episode seeds in N contiguous parts, each a batch in its own
process, the rows merged back in seed order: the rows of one process, whatever N (an episode's row on the batch
depends on its seed only, not on its row or batch: docs/performance.md, "The shield on the batch")."""

from __future__ import annotations

import pytest

from tests.conftest import conf
from tests.test_bad_input import check_line

VALIDATION = 1_000_000


def test_the_parts_are_contiguous_in_order_and_cover_every_seed():
    from eval.batched import chunks

    seeds = range(VALIDATION, VALIDATION + 7)
    parts = chunks(seeds, 3)
    assert [list(p) for p in parts] == [[VALIDATION, VALIDATION + 1], [VALIDATION + 2, VALIDATION + 3],
                                        [VALIDATION + 4, VALIDATION + 5, VALIDATION + 6]]
    assert [len(p) for p in chunks(range(2), 4)] == [1, 1]  # more workers than episodes: no empty part


@pytest.mark.slow  # two spawned workers, each importing the stack: ~30 s alone at load 2.4
def test_two_workers_give_the_rows_of_one_process():
    """7 shielded episodes, 2 at a time: in 2 workers (parts of 3 and 4 seeds, each refilling its batch) the same
    rows, every column, in seed order and numbered as in one process; a part dropped or merged out of order fails."""
    from tests.test_batched_shield import _plan

    from eval.batched import run_episodes_batched

    plan, env, policy = _plan("always_proceed+aeb")
    env.close()
    seeds = range(VALIDATION, VALIDATION + 7)
    one = run_episodes_batched(conf("env", "left_turn"), plan, policy, seeds, 2, "a", progress=False)
    got: list[dict] = []
    two = run_episodes_batched(conf("env", "left_turn"), plan, policy, seeds, 2, "a", progress=False, out=got,
                               workers=2)
    assert [r["seed"] for r in two] == list(seeds) and [r["episode"] for r in two] == list(range(7))
    assert repr(two) == repr(one) and repr(got) == repr(one)  # repr: NaN columns compare too
    assert sum(r["interventions"] for r in one) > 0  # the shield acted in these episodes


@pytest.mark.slow  # two spawned workers: ~15 CPU-s
def test_a_worker_that_cannot_build_the_env_is_said_by_the_parent():
    """A worker's failure (here an env value that only building the env checks: this function's own check looks
    at what the batch can run, the command line's check at the rest) comes back as the worker's own exception, not
    as a broken pool without the reason, and no row is made up."""
    from tests.test_batched_shield import _plan

    from av_gym.params import ParamError
    from eval.batched import run_episodes_batched

    plan, env, _ = _plan("always_proceed+aeb")
    env.close()
    got: list[dict] = []
    with pytest.raises(ParamError, match=r"env.duration must be a number in \(0, 600\], got -1"):
        run_episodes_batched({**conf("env", "left_turn"), "duration": -1}, plan, None,
                             range(VALIDATION, VALIDATION + 2), 1, "a", progress=False, out=got, workers=2)
    assert got == []


@pytest.mark.parametrize("argv, needle", [
    (["workers=2"], "workers=2 runs only with vec_env=batched"),
    (["workers=0", "vec_env=batched"], "workers must be an integer in [1, 64]"),
    (["workers=two", "vec_env=batched"], "workers must be an integer"),
])
def test_a_bad_workers_is_one_line(argv, needle, monkeypatch, capsys, tmp_path):
    monkeypatch.chdir(tmp_path)
    line = check_line("eval", argv, monkeypatch, capsys)
    assert needle in line, line


@pytest.mark.slow  # two evaluations as subprocesses, one spawning two workers: ~1 CPU-minute
def test_eval_with_two_workers_writes_the_one_process_results(tmp_path):
    """The command end to end: results.csv byte for byte the one process's, results.md saying the workers ran."""
    from tests.conftest import cli

    args = ["vec_env=batched", "agents=[always_proceed+aeb]", "episodes=5", f"seed={VALIDATION}", "split=validation",
            "progress_bar=false", "n_envs=2", "videos=false"]
    for workers in (1, 2):
        res = cli("eval", *args, f"workers={workers}", f"out_dir={tmp_path / str(workers)}", cwd=tmp_path)
        assert res.returncode == 0, res.stderr[-2000:]
    assert (tmp_path / "2" / "results.csv").read_bytes() == (tmp_path / "1" / "results.csv").read_bytes()
    assert "in 2 worker processes of 2 episodes each" in (tmp_path / "2" / "results.md").read_text()
    assert "worker processes" not in (tmp_path / "1" / "results.md").read_text()
