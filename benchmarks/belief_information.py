"""Which of the hidden draws the look-ahead oracle's choices depend on: ``belief_lookahead``'s GO/YIELD choices
against the oracle's on the same states, with its futures given the simulator's true draws one group at a time.

    python benchmarks/belief_information.py --episodes 64 --steps 10 --samples 16

States: ``--episodes`` validation episodes driven ``--steps`` env steps under YIELD (the ego at or near the stop
line, the planner reading every indicator). For each state: the oracle's label (the real GO future), and the
planner's (GO when at most ``--threshold`` of its K futures collide) with its futures as drawn, and with the true
routes, the true behaviour (IDM exponent, set-point, regulation hold), both, and both plus the real generators (the
future spawns). Prints the share of states where each agrees with the oracle, and where the planner agrees with
itself on another seed (its K futures drawn again): how noisy one label is on these states (not a ceiling for a
student: a predictor of the label's GO probability agrees with a label more than a second draw of it does)."""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

GROUPS = {"drawn": [], "true routes": ["route", "rpos", "tlane"], "true behaviour": ["delta", "target", "yielding"],
          "true routes + behaviour": ["route", "rpos", "tlane", "delta", "target", "yielding"],
          "+ true spawns (the oracle)": ["route", "rpos", "tlane", "delta", "target", "yielding", "rngs"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=64)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--samples", type=int, default=16)
    ap.add_argument("--threshold", type=float, default=0.05)
    args = ap.parse_args()

    from agents.batched_oracle import oracle_labels
    from agents.belief import BeliefLookaheadParams, BeliefPlanner, play_go_fast
    from av_gym.batched.vec_env import BatchedLeftTurnBatch, meta_actions
    from av_gym.seeds import seeds
    from av_gym.wrappers import GO, YIELD
    from benchmarks.belief_planner import stacks

    env, sensors, _ = stacks()
    B, K = args.episodes, args.samples
    venv = BatchedLeftTurnBatch(env, sensors, None, B, pool=0)
    obs = venv.play(iter(seeds("validation", B)))
    planner = BeliefPlanner(BeliefLookaheadParams(samples=K, threshold=args.threshold), n_rows=B)
    for _ in range(args.steps):
        live = np.nonzero(~venv.idle)[0]
        planner.read(venv.engine, live, obs["intent"][live])
        obs, _, _, _ = venv.step(meta_actions(np.full(B, YIELD), obs["turn"]))
    e = venv.engine
    rows = np.nonzero(~venv.idle)[0]
    planner.read(e, rows, obs["intent"][rows])
    oracle = oracle_labels(e, rows)[0]
    true = e.traffic.subset(np.repeat(rows, K))
    print(f"{len(rows)} states, oracle GO on {np.mean(oracle == GO):.2f}; planner K={K}, threshold {args.threshold}")
    again = BeliefPlanner(BeliefLookaheadParams(samples=K, threshold=args.threshold, seed=1), n_rows=B)
    again.counts = planner.counts  # the same readings, other futures
    same = np.mean(again.labels(e, rows) == planner.labels(e, rows))
    print(f"  {'the planner on another seed':28s} agrees with the planner on {same:.3f}")
    for label, names in GROUPS.items():
        f = planner.futures(e, rows)
        for name in names:
            if name == "rngs":
                f.rngs = [copy.deepcopy(e.rngs[r]) for r in np.repeat(rows, K)]
            else:
                setattr(f.traffic, name, getattr(true, name).copy())
        p = 1.0 - play_go_fast(f).reshape(len(rows), K).mean(axis=1)
        choice = np.where(p <= args.threshold + 1e-12, GO, YIELD)
        print(f"  {label:28s} agrees with the oracle on {np.mean(choice == oracle):.3f}")


if __name__ == "__main__":
    main()
