"""A first-use check that the batch detector's compiled draws are numpy's, on this machine's numpy and numba.

The batch's detector draws each frame in one compiled call (:func:`av_gym.sensors.kernels.frame_draws_span`), which
must take from each env's generator exactly the numbers the per-env detector's numpy calls take
(:func:`av_gym.sensors.detector.frame_draws`), or the batch silently runs other episodes than the per-env stack.
numba's ``np.random.Generator`` methods reimplement numpy's samplers; that they agree was observed on numba 0.68.1 /
numpy 2.4.6, and is promised by neither (numba 0.68's own Poisson sampler for lam >= 10 does not agree, see
:func:`~av_gym.sensors.kernels.poisson`). So before the batch first draws with the kernel, :func:`compiled_draws`
runs both on generators from one fixed SeedSequence, over a few hundred draws of each kind the detector makes
(miss-chain uniforms, standard normals, Poisson counts at means below and above numpy's switch to PTRS at 10, and
the clutter's uniforms), and compares the detections, every draw, the chains and the generators' final states.
On any difference it drops ``"draws"`` from :data:`av_gym.sensors.detector.KERNELS` (the batch then draws with
:func:`~av_gym.sensors.detector.frame_draws`, the per-env detector's own code) and warns once, in one line.
"""

from __future__ import annotations

import dataclasses
import warnings

import numba
import numpy as np

from av_gym.sensors import detector as _detector
from av_gym.sensors import kernels as _kernels
from av_gym.sensors.detector import DetectorParams, frame_draws, miss_chain

SEED = 20261130
"""The check's SeedSequence entropy (fixed: the check is the same every process)."""
RATES = (0.0, 0.2, 0.5, 3.0, 9.99, 10.0, 12.0, 30.0, 45.0)
"""Clutter means (false positives per frame) the frames cycle through: numpy's product-of-uniforms Poisson sampler
below 10 (none drawn at 0), its PTRS from 10 on."""
FRAMES, ROAD_USERS = 180, 12
"""Frames drawn (each its Poisson count: 20 per mean) and road users per frame (the same ids every frame, so that
the miss chains step on: 1,953 chain uniforms, 1,125 detections of 7 normals, 2,145 false positives of 3
uniforms each)."""
POISSON_SEEDS, POISSON_DRAWS = (16, 69, 103), 400
"""Generators that reach PTRS's rare branch within 400 draws at mean 10 (a candidate in (-1, 0), about one draw in
3e4-1e5), which the frames' 80 draws at means >= 10 do not: numba 0.68's own sampler, which truncates that candidate
where numpy floors it, first differs from numpy there at draws 224, 115 and 13."""

_RESULT: list[str | None] = []  # once per process: [None] agreed, [reason] differed


def compiled_draws() -> bool:
    """Whether the batch's detector draws with the compiled kernel: ``"draws"`` in the detector's ``KERNELS``, and
    the kernel's draws equal numpy's here (:func:`draws_differ`, run on the first call of the process; on a
    difference, or an exception from the kernel, ``"draws"`` is dropped from ``KERNELS`` and one warning says
    why)."""
    if "draws" not in _detector.KERNELS:
        return False
    if not _RESULT:
        try:
            _RESULT.append(draws_differ())
        except Exception as e:  # e.g. a numba that cannot compile the kernel: numpy's draws still serve
            first = (str(e).strip().splitlines() or [""])[0]
            _RESULT.append(f"the kernel raised {type(e).__name__}: {first}")
        if _RESULT[0] is not None:
            _detector.KERNELS.discard("draws")
            warnings.warn(f"the detector's compiled draws differ from numpy's (numpy {np.__version__}, numba "
                          f"{numba.__version__}): {_RESULT[0]}; the batch draws with numpy instead (the same numbers, "
                          f"slower)", RuntimeWarning, stacklevel=2)
    return _RESULT[0] is None


def _frames(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The check's road users: vehicle ids (R,), and per frame which are in view and which hidden (F, R)."""
    keys = np.arange(1, ROAD_USERS + 1, dtype=np.int64) * 7
    return keys, rng.random((FRAMES, ROAD_USERS)) < 0.9, rng.random((FRAMES, ROAD_USERS)) < 0.1


def draws_differ() -> str | None:
    """None if :func:`~av_gym.sensors.kernels.frame_draws_span` draws what :func:`frame_draws` draws (numpy's
    ``Generator``) on :data:`FRAMES` frames of :data:`ROAD_USERS` road users in bursty miss chains, clutter at the
    means :data:`RATES`, both from generators of one fixed SeedSequence; else which draw differed first."""
    differ = _poisson_differs()
    if differ is not None:
        return differ
    keys, in_view, hidden = _frames(np.random.default_rng(np.random.SeedSequence([SEED, 0])))
    base = DetectorParams(miss_rate=0.3, burst_length=3.0, fov_deg=120.0)
    params = [dataclasses.replace(base, clutter_rate=rate) for rate in RATES]
    reference = _Drawer(base)
    numpy_rng, kernel_rng = (np.random.default_rng(np.random.SeedSequence([SEED, 1])) for _ in range(2))
    chain: dict = {}
    state, owner = np.zeros(int(keys.max()) + 1, np.bool_), np.full(int(keys.max()) + 1, -1, np.int64)
    src, frame_of, draws = np.empty(ROAD_USERS, np.int64), np.empty(ROAD_USERS, np.int64), np.empty((ROAD_USERS, 7))
    room = 3 * int(max(RATES)) + 16  # a frame's false positives (mean <= 45): more than 151, P < 1e-30 (not on these
    # fixed draws), would only fail the check (the kernel leaves them undrawn), to numpy's draws' side
    clutter, clutter_frame = np.empty((room, 3)), np.empty(room, np.int64)
    for f in range(FRAMES):
        reference.params = params[f % len(RATES)]
        ids, want_draws, want_clutter = frame_draws(reference, numpy_rng, chain, keys.tolist(), in_view[f],
                                                    hidden[f])
        n, n_c, _ = _kernels.frame_draws_span(
            kernel_rng, state, owner, 1, keys, np.ascontiguousarray(in_view[f]), np.ascontiguousarray(hidden[f]),
            0, ROAD_USERS, reference.miss_rate, reference.p, reference.q, reference.params.clutter_rate,
            reference.half_fov, f, src, frame_of, draws, 0, clutter, clutter_frame, 0)
        differ = _compare(f, ids, want_draws, want_clutter, src[:n], draws[:n], clutter[:n_c])
        if differ is None and any(bool(state[k]) != chain[k] for k in chain):
            differ = f"frame {f}: the miss chains"
        if differ is not None:
            return differ
    if numpy_rng.bit_generator.state != kernel_rng.bit_generator.state:
        return "the generators' states after all draws"
    return None


def _poisson_differs() -> str | None:
    """None if :func:`~av_gym.sensors.kernels.poisson` at mean 10 gives numpy's counts and generator states on the
    generators of :data:`POISSON_SEEDS`; else where it first differed."""
    for seed in POISSON_SEEDS:
        ours, theirs = np.random.default_rng(seed), np.random.default_rng(seed)
        got = np.array([_kernels.poisson(ours, 10.0) for _ in range(POISSON_DRAWS)])
        want = theirs.poisson(10.0, POISSON_DRAWS)
        if not np.array_equal(got, want):
            return f"the Poisson count at mean 10 (generator {seed}, draw {int(np.argmax(got != want))})"
        if ours.bit_generator.state != theirs.bit_generator.state:
            return f"the generator's state after Poisson draws at mean 10 (generator {seed})"
    return None


class _Drawer:
    """What :func:`frame_draws` reads of a detector (:class:`~av_gym.sensors.detector.FrameDrawer`), from a
    parameter set: its miss chain, miss rate and half field of view (rad)."""

    def __init__(self, params: DetectorParams) -> None:
        self.params, self.miss_rate = params, params.miss_rate
        self.p, self.q = miss_chain(params.miss_rate, params.burst_length)
        self.half_fov = float(np.radians(params.fov_deg) / 2)


def _compare(f: int, ids: list[int], want_draws: list[np.ndarray], want_clutter: list[tuple], src: np.ndarray,
             draws: np.ndarray, clutter: np.ndarray) -> str | None:
    """Which of frame ``f``'s draws differ (numpy's ``ids``, ``want_draws``, ``want_clutter`` against the kernel's
    ``src``, ``draws``, ``clutter``), or None."""
    if src.tolist() != ids:
        return f"frame {f}: the miss chains' uniforms (detections {src.tolist()} against numpy's {ids})"
    if not np.array_equal(draws, np.array(want_draws).reshape(-1, 7)):
        return f"frame {f}: the standard normals"
    if len(clutter) != len(want_clutter):
        return f"frame {f}: the Poisson count ({len(clutter)} against numpy's {len(want_clutter)})"
    want = np.array(want_clutter).reshape(-1, 3)
    for column, kind in enumerate(("random()", "uniform(-half_fov, half_fov)", "uniform(-pi, pi)")):
        if not np.array_equal(clutter[:, column], want[:, column]):
            return f"frame {f}: the clutter's {kind}"
    return None
