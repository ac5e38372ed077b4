"""Seed splits: which episode seeds may be learnt from, which may be looked at to decide, which may be reported.

An episode is fixed by its seed (the env, every sensor and the shield reseed from it), so a split of the seed
integers is a split of the episodes:

- ``train`` [0, 1,000,000): everything that learns sees only these: PPO's env streams (``seed`` + steps done),
  the teacher's demonstrations for cloning, PilotNet's expert laps, ``train.pid_search``'s laps.
- ``validation`` [1,000,000, 2,000,000): everything that selects or tunes looks only at these: the periodic
  evaluation during training (``best.zip``), the brief evaluation after it, sweeps, ad-hoc ``python -m eval``
  (its default), the shield's development runs.
- ``test`` [2,000,000, 3,000,000): the reported tables (``docs/results.md``), and nothing else. Look at a test
  result only to report it; a design change made after looking is tuned on it, and its next report needs seeds
  that were not looked at (the rest of the range; the range itself is fixed and documented so tables compare).

The ranges are contiguous, half-open and checked disjoint at import (:data:`SPLITS`). Seeds below 1,000,000
include every range the project used before the splits existed (1000+ for its tables, 100000+ for checkpoint
selection, 500000+ for demonstrations): those tables were tuned on their seeds and are kept as train-split history.
"""

from __future__ import annotations

from typing import Literal

Split = Literal["train", "validation", "test"]

SPLITS: dict[str, range] = {
    "train": range(0, 1_000_000),
    "validation": range(1_000_000, 2_000_000),
    "test": range(2_000_000, 3_000_000),
}
NAMES: tuple[str, ...] = tuple(SPLITS)

# Disjoint by construction: each range starts where the one before it stops.
_ORDERED = list(SPLITS.values())
assert all(a.stop <= b.start for a, b in zip(_ORDERED, _ORDERED[1:])), "seed splits overlap"

DEMONSTRATIONS = 500_000  # first train seed of a teacher's demonstrations (cloning): away from PPO's own streams


def split_range(split: str) -> range:
    """The seed range of ``split``; ValueError naming the allowed splits otherwise."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {list(NAMES)}, got {split!r}")
    return SPLITS[split]


def split_of(seed: int) -> str | None:
    """The split ``seed`` lies in (None outside every split)."""
    for name, r in SPLITS.items():
        if int(seed) in r:
            return name
    return None


def seeds(split: str, n: int, first: int | None = None, field: str = "seed", count: str = "episodes") -> range:
    """``n`` consecutive seeds of ``split`` from ``first`` (default: the split's start). ValueError, naming
    ``field`` (the first seed's setting) and ``count`` (the setting ``n`` came from), when they do not all lie in
    the split: a reported table cannot borrow tuning seeds, and an evaluation used to decide cannot peek at the test
    range."""
    r = split_range(split)
    start = r.start if first is None else int(first)
    if n < 0:
        raise ValueError(f"the number of episodes must be >= 0, got {n}")
    named = "" if count == "episodes" else f" ({count})"
    leaves = f"{field}={start} with {n} episodes{named} leaves split {split!r} (seeds {r.start}..{r.stop - 1}); "
    if start in r and start + n > r.stop:  # the seed is fine; the episodes run past the split's end
        raise ValueError(f"{leaves}give {count} <= {r.stop - start} (what the split leaves from {field}={start})"
                         + (f", or an earlier {field}" if start > r.start else ""))
    if start not in r:
        raise ValueError(f"{leaves}give {field} in that range, or leave it out to start at {r.start}")
    return range(start, start + n)


def config_seeds(split: str, n: int, first: int | None, field: str, count: str = "episodes") -> range:
    """:func:`seeds` for a command's settings: a :class:`av_gym.errors.ConfigError` (one line, exit 2 on the
    command line) instead of a ValueError."""
    from av_gym.errors import ConfigError

    try:
        return seeds(split, n, None if first is None else int(first), field=field, count=count)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def train_seed(base: int, offset: int = 0) -> int:
    """A training env stream's seed: ``base + offset`` (e.g. ``seed`` + steps already done on a resume) folded
    into the train range, so no run length or seed moves a training episode into validation or test."""
    r = SPLITS["train"]
    return r.start + (int(base) + int(offset)) % len(r)


def describe() -> str:
    """One line per split, for help texts and results pages."""
    return "; ".join(f"{k} {r.start}..{r.stop - 1}" for k, r in SPLITS.items())
