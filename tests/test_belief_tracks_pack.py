"""The planner on tracks packs the futures' start (agents/track_prior.py, ``TrackBelief._pack``): every per-slot
array moves with its road user, so a slot's filter covariance and ghost mark are its own track's."""

from __future__ import annotations

import numpy as np

from agents.belief import BeliefLookaheadParams
from agents.track_prior import along_heading
from av_gym.batched.perception import tracks_observation
from tests.test_belief_tracks import _batch

# (x, y, vx, vy) m, m/s; tracker id; confirmed; detector frames since its last update; filter covariance scale.
# The ego stands at about (2, 15) heading south. A is nearest, detected now and off the line of sight to G; G, an
# oncoming track missed 3 frames in plain view, is a ghost with ``ghost`` 2 and leaves a hole inside the described
# block; C is confirmed beyond it; T is tentative (after the 16 described slots).
TRACKS = {"A": ((10.0, 5.0, 0.0, -4.0), 1001, True, 0, 0.1),
          "G": ((-2.0, -25.0, 0.0, 9.0), 1002, True, 3, 0.4),
          "C": ((-10.0, -45.0, 0.0, 8.0), 1003, True, 0, 0.9),
          "T": ((-6.0, -10.0, 3.0, 5.0), 1004, False, 0, 1.6)}


def _covariance(scale: float) -> np.ndarray:
    """A filter covariance of ``[x, y, vx, vy]`` (m², m²/s, m²/s²), distinct per track and correlated."""
    P = np.diag([1.0, 2.0, 3.0, 4.0]) * scale
    P[0, 2] = P[2, 0] = P[1, 3] = P[3, 1] = 0.5 * scale
    return P


def _plant(venv, r: int) -> None:
    """Row ``r``'s tracker holds exactly the tracks of :data:`TRACKS`, in that order."""
    trk, p, e = venv.perception.tracker, venv.perception, venv.engine
    rate = p.detector.params.rate_hz
    now = e.ticks[r] / e.config["simulation_frequency"]
    trk.n[r] = len(TRACKS)
    for k, (state, tid, confirmed, missed, scale) in enumerate(TRACKS.values()):
        trk.x[r, k] = np.array(state, float)[:, None]
        trk.P[r, k] = _covariance(scale)
        trk.t[r, k], trk.t_update[r, k] = now, trk.fused_at[r] - missed / rate
        trk.length[r, k], trk.width[r, k], trk.heading[r, k] = 5.0, 2.0, np.arctan2(state[3], state[2])
        trk.hits[r, k], trk.confirmed[r, k], trk.id[r, k] = (5 if confirmed else 1), confirmed, tid
    s = int(e.ego_slot([r])[0])
    ego = np.array([[e.traffic.x[r, s], e.traffic.y[r, s]]])
    p.last_tracks[[r]] = tracks_observation(*trk.tracks([r]), ego, p.max_tracks)


def test_the_packing_carries_each_slots_covariance_and_ghost_mark_with_its_track():
    """A ghost inside the described block (G) and a tentative track after it (T): after the read packs the futures'
    start, the road users fill slots 1-3 (A, C, T, their order kept) and G sits behind them; every slot holding a
    track has that track's covariance along its heading, and the ghost mark is on G's slot alone. With the
    covariances or the ghost mask left in their slots before the packing, C and T would carry G's and a
    non-user's covariance, and the mark would sit on C."""
    venv, planner, obs, rows = _batch([420_001, 420_002], 45, BeliefLookaheadParams(
        samples=4, unseen=0.0, ghost=2, tentative="road_user", track_spread=1.0))
    for r in rows:
        _plant(venv, int(r))
    planner.read(venv.engine, rows, np.zeros_like(obs["intent"])[rows])
    tb = planner.tracks
    t = tb.engine.traffic
    by_vid = {tid + 1: (name, _covariance(scale)) for name, (_, tid, _, _, scale) in TRACKS.items()}
    for r in rows:
        held = t.alive[r] | tb.ghost[r]  # the slots holding the ego or one of the tracks
        names = [by_vid[v][0] if v in by_vid else None for v in t.vid[r]]
        assert [names[j] for j in np.flatnonzero(held)] == [None, "A", "C", "T", "G"]
        assert np.flatnonzero(t.alive[r]).tolist() == [0, 1, 2, 3]
        np.testing.assert_array_equal(tb.along[r, 0], np.zeros((2, 2)))  # the ego's slot: no filter
        for j in np.flatnonzero(held)[1:]:
            np.testing.assert_allclose(tb.along[r, j], along_heading(by_vid[t.vid[r, j]][1], t.h[r, j]),
                                       rtol=1e-12, atol=1e-12, err_msg=f"slot {j} ({names[j]})")
        assert [names[j] for j in np.flatnonzero(tb.ghost[r])] == ["G"]
        assert [names[j] for j in np.flatnonzero(tb.tent[r])] == ["T"]
