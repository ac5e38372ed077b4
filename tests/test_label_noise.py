"""benchmarks/label_noise.py: the agreement statistics on constructed cases whose answers are known."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from math import comb
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binom

from av_gym.wrappers import GO, YIELD

ROOT = Path(__file__).resolve().parents[1]


def _script():
    """benchmarks/label_noise.py as a module (a script, not a package: loaded by path, as tests/test_dagger.py loads
    oracle_labels)."""
    spec = importlib.util.spec_from_file_location("label_noise", ROOT / "benchmarks" / "label_noise.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


ln = _script()


def test_pair_agreement_counts_each_pair_of_replicates_once():
    two = np.array([[GO, GO], [GO, YIELD], [YIELD, YIELD]])
    assert ln.pair_agreement(two).tolist() == [1.0, 0.0, 1.0]
    # 3 replicates, 2 GO: 1 of 3 pairs agree; 4 replicates 2/2: 2 of 6; 4 replicates 3/1: 3 of 6
    many = np.array([[GO, GO, YIELD, YIELD], [GO, GO, GO, YIELD], [GO, GO, GO, GO]])
    assert ln.pair_agreement(many) == pytest.approx([2 / 6, 3 / 6, 1.0])
    assert ln.pair_agreement(np.array([[GO, GO, YIELD]])) == pytest.approx([1 / 3])
    with pytest.raises(ValueError, match="at least 2 replicates"):
        ln.pair_agreement(np.array([[GO], [YIELD]]))


def test_p_label_go_is_the_chance_that_k_of_the_futures_pass_the_threshold():
    # threshold 0.05 at K=16: GO only when none of the 16 collide; 1 collision in 64 futures: 48/64 of the
    # 16-subsets miss it
    assert ln.p_label_go([1], [64], 16, 0.05)[0] == pytest.approx(comb(63, 16) / comb(64, 16))
    assert ln.p_label_go([1], [64], 16, 0.05)[0] == pytest.approx(0.75)
    assert ln.p_label_go([0, 64], [64, 64], 16, 0.05).tolist() == pytest.approx([1.0, 0.0])
    # at K=64 the same threshold allows 3 of 64 (0.05 x 64 = 3.2): with 3 of 64 drawn the label is surely GO, 4 never
    assert ln.p_label_go([3, 4], [64, 64], 64, 0.05).tolist() == pytest.approx([1.0, 0.0])
    # exactly on the threshold counts as GO (agents/belief.py: share <= threshold): 0.25 x 16 = 4 collisions allowed
    assert ln.p_label_go([4, 5], [16, 16], 16, 0.25).tolist() == pytest.approx([1.0, 0.0])
    with pytest.raises(ValueError, match="at least 16 futures"):
        ln.p_label_go([0], [8], 16, 0.05)


def test_bins_separate_zero_risk_and_close_on_the_right():
    risk = np.array([0.0, 0.01, 0.025, 0.03, 0.05, 0.2, 0.5, 1.0])
    assert ln.bins_of(risk).tolist() == [0, 1, 1, 2, 2, 4, 5, 5]


def _synthetic(n: int, rng: np.random.Generator) -> tuple[dict, np.ndarray]:
    """States with known GO risks p: two K=16 labels and two K=64 draws each, as the planner's futures would give
    (each future collides with probability p, independently); returns them and q = P(K=16 label is GO)."""
    p = rng.choice([0.0, 0.01, 0.03, 0.05, 0.1, 0.5], size=n)
    c16 = rng.binomial(16, p[:, None], size=(n, 2))
    c64 = rng.binomial(64, p[:, None], size=(n, 2))
    label = lambda c, K: np.where(c <= np.floor(0.05 * K + 1e-9), GO, YIELD)  # noqa: E731
    states = {"labels": {16: label(c16, 16), 64: label(c64, 64)}, "collided": {16: c16, 64: c64},
              "student": np.full(n, GO)}
    return states, (1.0 - p) ** 16


def test_the_table_recovers_known_agreements_and_a_denoised_label_beats_self_agreement():
    """Self-agreement estimates E[q² + (1-q)²]; the predictor from the K=64 futures reaches close to E[max(q, 1-q)],
    which is larger: the label's self-agreement is not the ceiling of a student's agreement with it."""
    states, q = _synthetic(40_000, np.random.default_rng(7))
    rows = ln.table(states, 0.05)
    first = rows[0]
    assert first["risk"] == "all" and first["states"] == 40_000
    self_expected = float(np.mean(q**2 + (1 - q) ** 2))
    ceiling = float(np.mean(np.maximum(q, 1 - q)))
    assert first["self_K16"] == pytest.approx(self_expected, abs=0.01)
    # the predictor's own expected agreement, exactly: its GO given c of the 128 K=64 futures collide, c ~ Binom
    c = np.arange(129)
    go = ln.p_label_go(c, np.full(129, 128), 16, 0.05) > 0.5
    # per distinct risk (6 of them), not per state: the same sums, without 40,000 pmf evaluations
    p, back = np.unique(1.0 - q ** (1 / 16), return_inverse=True)
    p_go = np.array([binom.pmf(c, 128, pi)[go].sum() for pi in p])[back]
    assert first["best_K16"] == pytest.approx(float(np.mean(p_go * q + (1 - p_go) * (1 - q))), abs=0.01)
    assert ceiling - 0.03 < first["best_K16"] <= ceiling + 0.005  # a lower bound, near the ceiling
    assert first["best_K16"] > first["self_K16"] + 0.03
    # the student here always says GO: its agreement is the share of GO labels
    assert first["student_K16"] == pytest.approx(float(np.mean(q)), abs=0.01)
    assert first["label_go"] == pytest.approx(float(np.mean(q)), abs=0.01)
    # zero risk: every label GO, all agree
    zero = next(r for r in rows if r["risk"] == "0")
    assert zero["self_K16"] == zero["self_K64"] == zero["best_K16"] == zero["student_K16"] == 1.0
    assert sum(r["states"] for r in rows[1:]) == 40_000


def test_the_student_is_scored_against_the_denoised_label():
    states, q = _synthetic(5_000, np.random.default_rng(3))
    rows = ln.table(states, 0.05)
    best = np.where(ln.p_label_go(states["collided"][64].sum(axis=1), 128, 16, 0.05) > 0.5, GO, YIELD)
    states["student"] = best
    assert ln.table(states, 0.05)[0]["student_best"] == 1.0
    states["student"] = np.where(best == GO, YIELD, GO)
    assert ln.table(states, 0.05)[0]["student_best"] == 0.0
    assert rows[0]["student_best"] == pytest.approx(float(np.mean(best == GO)))


def test_by_unseen_groups_the_students_errors_on_clear_cut_states():
    """Four states: clear GO (risk 0), clear YIELD (risk 1), near the threshold (risk 1/16), each with 0, 1 or 3
    road users left out of the features; the student wrong on the clear GO with 1 unseen and on the near state."""
    states = {"labels": {16: np.array([[GO, GO], [YIELD, YIELD], [GO, YIELD], [GO, GO]])},
              "collided": {16: np.array([[0, 0], [16, 16], [1, 1], [0, 0]])},
              "student": np.array([YIELD, YIELD, YIELD, GO]), "unseen": np.array([1, 0, 0, 3])}
    rows = ln.by_unseen(states)
    assert [(r["unseen"], r["states"]) for r in rows] == [("0", 2), ("1", 1), ("2+", 1)]
    # unseen 0: the clear YIELD answered right, the near state answered wrong (not clear-cut: no clear error)
    assert rows[0]["student_K16"] == 0.5 and rows[0]["clear_error"] == 0.0
    assert rows[1]["student_K16"] == 0.0 and rows[1]["clear_error"] == 1.0
    assert rows[2]["student_K16"] == 1.0 and rows[2]["clear_error"] == 0.0


BAD_ARGUMENTS = [(["--repeats", "1"], "--repeats must be >= 2"),
                 (["--samples", "64", "16"], "--samples must be >= 1 with the labels' K first"),
                 (["--episodes", "0"], "--episodes must be >= 1")]


@pytest.mark.parametrize("args, says", BAD_ARGUMENTS)
def test_bad_arguments_are_one_line_and_exit_2_in_process(args, says, capsys):
    """The argument checks themselves, in this process (the script's start-up imports cost ~2 s a subprocess)."""
    with pytest.raises(SystemExit) as stop:
        ln.main(args)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert says in err and says in err.strip().splitlines()[-1]


@pytest.mark.slow  # ~2 s a case (the script's imports in a fresh interpreter); the checks run fast in process above
@pytest.mark.parametrize("args, says", BAD_ARGUMENTS)
def test_bad_arguments_are_one_line_and_exit_2(args, says):
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "label_noise.py"), *args],
                         capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 2
    assert says in out.stderr
