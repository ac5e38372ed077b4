"""A track's true state, the one definition the tracing tools share (belief_tracks_state.py plays the planner with
it, belief_tracks_confirm.py asks what a decision would have been with it): each road user the planner has (a
confirmed or tentative track in the futures' start, ``planner.tracks.engine``) is matched to the nearest simulator
vehicle within a radius (m), and takes that vehicle's place, heading, speed, acceleration and lane; its set-point
becomes its true speed (as a track's set-point is its tracked speed) and its route's first lane its lane. What the
simulator keeps hidden (routes ahead, set-points, IDM draws) stays the planner's: a perfect filter estimates a
car's state, not its driver's intentions."""

from __future__ import annotations

import copy

import numpy as np

MATCH_M = 3.0  # default match radius (m): a track within it of a vehicle is that vehicle's
STATE = ("x", "y", "h", "v", "acc", "lane", "tlane")  # the traffic fields a filter estimates


def nearest_cars(tracks_engine, engine, r: int, radius: float = np.inf) -> dict[int, tuple[int, float]]:
    """Track slot -> (simulator slot, distance m) for row ``r``: the nearest simulator vehicle (ego excluded) of each
    road user the planner has, for those with one within ``radius`` m."""
    t, s = tracks_engine.traffic, engine.traffic
    cars = np.flatnonzero(s.alive[r] & ~s.ego[r])
    users = np.flatnonzero(t.alive[r] & ~t.ego[r])
    if not len(cars) or not len(users):
        return {}
    d = np.hypot(t.x[r, users][:, None] - s.x[r, cars][None], t.y[r, users][:, None] - s.y[r, cars][None])
    nearest, dist = np.argmin(d, axis=1), d.min(axis=1)
    return {int(j): (int(cars[n]), float(m)) for j, n, m in zip(users, nearest, dist) if m <= radius}


def give_true_state(traffic, sim, r: int, j: np.ndarray | int, i: np.ndarray | int) -> None:
    """Track slots ``j`` of row ``r`` in ``traffic`` take simulator slots ``i``'s state (:data:`STATE`), the true
    speed (m/s, at least 0) as set-point and the true lane as the route's first lane; in place."""
    for name in STATE:
        getattr(traffic, name)[r, j] = getattr(sim, name)[r, i]
    traffic.target[r, j] = np.maximum(sim.v[r, i], 0.0)
    traffic.route[r, j, 0] = sim.lane[r, i]


def true_states(tracks_engine, engine, rows: np.ndarray, radius: float = MATCH_M) -> int:
    """Every road user of ``rows`` in ``tracks_engine`` within ``radius`` m of a simulator vehicle of ``engine``
    given the nearest one's state (:func:`give_true_state`), in place; returns how many were replaced."""
    done = 0
    for r in rows:
        matched = nearest_cars(tracks_engine, engine, int(r), radius)
        if matched:
            j = np.fromiter(matched, int)
            give_true_state(tracks_engine.traffic, engine.traffic, int(r), j, [matched[k][0] for k in matched])
            done += len(j)
    return done


def decision_p(planner, engine, rows, held) -> np.ndarray:
    """GO's collision probability of ``rows`` (their held choices ``held``) as the planner's ``decide()`` judges it at
    a decision: its own :meth:`~agents.belief.BeliefPlanner._decision_collision`, not ``go_collision`` (which would
    demand ``track_margin`` of a held GO that ``track_margin_scope`` start judges on contact alone). The tracing
    tools ask every GO collision probability, counterfactual or not, through this."""
    return planner._decision_collision(engine, np.asarray(rows, dtype=int).reshape(-1), np.asarray(held).reshape(-1))


def go_with_true_state(planner, engine, r: int, j: int, i: int, held: int) -> float:
    """GO's collision probability for row ``r`` (holding ``held``, :func:`decision_p`) with track slot ``j``'s state
    that of simulator vehicle ``i`` (:func:`give_true_state`); the planner's own futures' start is left as it was."""
    saved = planner.tracks.engine
    e = copy.copy(saved)
    e.traffic = saved.traffic.subset(np.arange(saved.B))
    give_true_state(e.traffic, engine.traffic, r, j, i)
    planner.tracks.engine = e
    try:
        return float(decision_p(planner, engine, r, held)[0])
    finally:
        planner.tracks.engine = saved
