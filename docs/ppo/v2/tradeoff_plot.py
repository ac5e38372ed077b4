"""The round-2 trade-off plot (docs/ppo/v2/tradeoff.png) from rows already measured, without re-running the rule sweep.

    python docs/ppo/v2/tradeoff_plot.py

Reads the per-episode rows of the 500 test episodes (seeds 1000-1499: ``headline_v2b_results.csv``, three seeds of
ppo_turn on the batched simulator and gap_acceptance at its default t_gap = 4 s; ``headline_results.csv``, the two
per-env seeds and their +aeb rows) and the rule sweep's rows (``tradeoff_rule_sweep.csv``, written by
``python -m eval.tradeoff ... --rule-sweep 2,3,6 --episodes 100 --seed 1000``: seeds 1000-1099), relabels them so
that seeds of one configuration share a colour (``name#seed``), and draws them with :func:`eval.tradeoff.plot`.
Points measured in earlier rounds on the same 500 seeds (docs/ppo.md's tables) are given as fixed points.
"""

from __future__ import annotations

import csv
from pathlib import Path

from eval.tradeoff import plot, points

HERE = Path(__file__).parent
RELABEL = {
    "gap_acceptance": "gap_acceptance t_gap=4s",
    **{f"checkpoints/ppo_turn_v2b_s{s}": f"ppo_turn (batched sim)#s{s}" for s in (1, 2, 3)},
    **{f"checkpoints/ppo_turn_v2_s{s}": f"ppo_turn (per-env sim)#s{s}" for s in (1, 2)},
    **{f"checkpoints/ppo_turn_v2_s{s}+aeb": f"ppo_turn (per-env sim)+aeb#s{s}" for s in (1, 2)},
}
# (collision, success) on seeds 1000-1499, measured in round 1 (docs/ppo.md, "Headline" of issue 7; stacks unchanged)
FIXED = {
    "always_proceed": (0.50, 0.50),
    "always_proceed+aeb": (0.06, 0.81),
    "lookahead (oracle)": (0.01, 0.92),
    "ppo_turn_perceived (round 1)": (0.09, 0.25),
    "ppo_turn_shielded (round 1)": (0.14, 0.26),
}


def main() -> None:
    rows = []
    for name in ("headline_v2b_results.csv", "headline_results.csv", "tradeoff_rule_sweep.csv"):
        with open(HERE / name, newline="") as f:
            for r in csv.DictReader(f):
                r["agent"] = RELABEL.get(r["agent"], r["agent"])
                rows.append(r)
    pts = points(rows)
    rule = sorted((k for k in pts if k.startswith("gap_acceptance t_gap=")),
                  key=lambda k: float(k.split("=")[1].rstrip("s")))
    for label, (c, s) in FIXED.items():
        pts[label] = (c, s, (c, c), (s, s), 0)
    for label, (c, s, _, _, n) in pts.items():
        print(f"{label:40s} n={n:4d}  collision {c:.3f}  success {s:.3f}")
    plot(pts, rule, HERE / "tradeoff.png", "Left turn in traffic, test seeds 1000+: safety vs progress")
    print(f"[tradeoff] {HERE / 'tradeoff.png'}")


if __name__ == "__main__":
    main()
