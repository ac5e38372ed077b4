"""Two points of benchmarks/belief_tracks_sweep.py on the same seeds, compared episode by episode.

    python benchmarks/belief_tracks_paired.py /tmp/preset.csv /tmp/candidate.csv [--out /tmp/pair.json]

Reads the two ``--rows`` CSVs (one row per episode: its seed, collision, success; both files the same seeds, each
once: an episode played under one point only has no pair) and prints one JSON line: each point's collision and
success rates, the exchanges (episodes that collided / arrived under only one of the two), the exact McNemar p of
each (a two-sided binomial test of the discordant pairs at 1/2: scipy.stats.binomtest; printed to two significant
figures, ``--out`` writes the same JSON with its full value), and success - collision of the second minus the first
with a paired 95 % BCa bootstrap interval over the per-episode differences (av_gym.metrics.stats.bootstrap_ci, a
seeded generator)."""

from __future__ import annotations

import argparse
import csv
import json
import sys

import numpy as np

BOOTSTRAP_SEED = 0  # the same two files give the same interval
RESAMPLES = 10_000


def fail(message: str) -> None:
    """One ``error:`` line on stderr, exit status 2 (bad input)."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def outcomes(path: str) -> dict[int, tuple[bool, bool]]:
    """seed -> (collision, success) of a sweep's ``--rows`` file (each seed once)."""
    try:
        with open(path, newline="") as fh:
            rows = [(int(r["seed"]), (_flag(r["collision"]), _flag(r["success"]))) for r in csv.DictReader(fh)]
    except (OSError, KeyError, ValueError) as exc:
        fail(f"{path}: a sweep --rows CSV with seed, collision and success columns is needed ({exc})")
    out = dict(rows)
    if len(out) != len(rows):
        fail(f"{path}: {len(rows) - len(out)} seeds appear more than once (one row per episode is needed)")
    return out


def _flag(text: str) -> bool:
    """A row's flag: True / False or a number (0 false)."""
    if text.strip().lower() in ("true", "false"):
        return text.strip().lower() == "true"
    return float(text) != 0.0


def mcnemar(only_a: int, only_b: int) -> float:
    """The exact two-sided McNemar p of ``only_a`` against ``only_b`` discordant pairs (1.0 when there are none)."""
    from scipy.stats import binomtest

    n = only_a + only_b
    return 1.0 if n == 0 else float(binomtest(only_a, n, 0.5).pvalue)


def compare(a: dict[int, tuple[bool, bool]], b: dict[int, tuple[bool, bool]], names: tuple[str, str] = ("a", "b"),
            ) -> dict:
    """The paired comparison of point ``b`` against point ``a``, which must have played the same seeds (``names``:
    the two files, for the error); each McNemar p unrounded."""
    from av_gym.metrics.stats import bootstrap_ci

    a_lacks, b_lacks = len(set(b) - set(a)), len(set(a) - set(b))
    if a_lacks or b_lacks:  # an episode of one point only has no pair: leaving it out would hide it
        fail(f"the two files must hold the same seeds: {names[0]} lacks {a_lacks} of {names[1]}'s, {names[1]} lacks "
             f"{b_lacks} of {names[0]}'s (a paired test needs each episode under both points)")
    seeds = sorted(a)
    if not seeds:
        fail("the two files hold no episode")
    ca, sa = (np.array([a[s][k] for s in seeds]) for k in (0, 1))
    cb, sb = (np.array([b[s][k] for s in seeds]) for k in (0, 1))
    d = (sb.astype(float) - cb) - (sa.astype(float) - ca)  # per episode: b's success - collision minus a's
    _, lo, hi = bootstrap_ci(d, 0.95, BOOTSTRAP_SEED, RESAMPLES)
    n = len(seeds)
    out = {"episodes": n}
    for name, c, s in (("a", ca, sa), ("b", cb, sb)):
        out[name] = {"collision": round(c.mean(), 4), "success": round(s.mean(), 4),
                     "s_minus_c": round(s.mean() - c.mean(), 4)}
    for what, x, y in (("collided", ca, cb), ("arrived", sa, sb)):
        only_a, only_b = int((x & ~y).sum()), int((~x & y).sum())
        out[what] = {"only_a": only_a, "only_b": only_b, "mcnemar_p": mcnemar(only_a, only_b)}
    out["b_minus_a_s_minus_c"] = {"mean": round(float(d.mean()), 4), "lo": round(lo, 4), "hi": round(hi, 4)}
    return out


def printed(result: dict) -> str:
    """:func:`compare`'s result as one JSON line, each McNemar p to two significant figures (a JSON number: 2.0e-05,
    0.31, 1.0), not rounded to decimals (a p of 2e-05 is not 0)."""
    shown = json.loads(json.dumps(result))
    for what in ("collided", "arrived"):  # a float of two significant figures: json writes 2.1e-05 as it is
        shown[what]["mcnemar_p"] = float(f"{result[what]['mcnemar_p']:.2g}")
    return json.dumps(shown)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="the first point's --rows CSV (e.g. the preset)")
    ap.add_argument("b", help="the second point's --rows CSV (e.g. a candidate)")
    ap.add_argument("--out", default=None, metavar="PATH", help="the result as JSON, p unrounded (a new file)")
    args = ap.parse_args()
    from av_gym.atomic import new_paths_or_exit

    new_paths_or_exit((args.out, "--out"))  # before the run: a taken path loses none of it
    result = compare(outcomes(args.a), outcomes(args.b), (args.a, args.b))
    print(printed(result), flush=True)  # first: a print cut short (Ctrl-C, a closed pipe) leaves no unseen --out
    if args.out:  # linked into place: a file that appeared at --out since the check above is kept, not replaced
        from av_gym.atomic import write_new_or_exit

        write_new_or_exit(args.out, json.dumps(result) + "\n", "--out")


if __name__ == "__main__":
    main()
