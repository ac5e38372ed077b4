"""How another road user's possible paths relate to the ego's planned path on highway-env's four-way intersection
(issue 17), read from the road network, never from the vehicle's motion.

Partner types (:func:`partner_type`), in this order of precedence:

- ``ahead`` / ``behind``: on a lane of the ego's route, in front of / behind the ego along it;
- ``merging``: its planned lanes join the ego's route further on (e.g. an oncoming car turning right into the
  ego's exit, or a car from the east going straight to the ego's exit);
- ``oncoming``: it comes from the approach opposite the ego's (straight across the ego's turn, or turning);
- ``crossing``: any other road user (from the left or the right approach, or leaving on another exit).

Node names are highway-env's intersection's: approach ``o{i}→ir{i}``, through the box ``ir{i}→il{j}``, exit
``il{j}→o{j}``.
"""

from __future__ import annotations

import numpy as np

PARTNER_TYPES = ("oncoming", "crossing", "merging", "ahead", "behind", "unknown")


def approach_of(lane_index) -> int | None:
    """The approach (0-3) a vehicle on ``lane_index`` came from, or None on an exit lane / an unknown road."""
    if not lane_index:
        return None
    a, b = str(lane_index[0]), str(lane_index[1])
    if a.startswith("o") and b.startswith("ir"):
        tag = b[2:]
    elif a.startswith("ir") and b.startswith("il"):
        tag = a[2:]
    else:
        return None
    return int(tag) if tag.isdigit() else None


def planned_lanes(vehicle) -> list[tuple]:
    """The lanes ``vehicle`` is on and plans to drive (its current lane, then the rest of its route)."""
    lane = getattr(vehicle, "lane_index", None)
    if lane is None:
        return []
    route = list(getattr(vehicle, "route", None) or [])
    key = lambda li: (li[0], li[1])  # noqa: E731 -- lane ids in a route may carry another lane number
    keys = [key(li) for li in route]
    rest = route[keys.index(key(lane)) + 1:] if key(lane) in keys else []
    return [tuple(lane), *[tuple(li) for li in rest]]


def route_position(network, route: list[tuple], starts: np.ndarray, lane_index, position) -> float | None:
    """Distance (m) along the ego's ``route`` (lane ``k`` begins at ``starts[k]``) of a point on one of its lanes;
    None when ``lane_index`` is not on the route."""
    keys = [(li[0], li[1]) for li in route]
    if lane_index is None or (lane_index[0], lane_index[1]) not in keys:
        return None
    k = keys.index((lane_index[0], lane_index[1]))
    s, _ = network.get_lane(route[k]).local_coordinates(np.asarray(position, dtype=float))
    return float(starts[k] + s)


def partner_type(vehicle, network, ego_route: list[tuple], ego_starts: np.ndarray, ego_s: float) -> str:
    """The partner type (module docstring) of ``vehicle`` relative to an ego at ``ego_s`` m along ``ego_route``."""
    lane = getattr(vehicle, "lane_index", None)
    if lane is None:
        return "unknown"
    s = route_position(network, ego_route, ego_starts, lane, vehicle.position)
    if s is not None:
        return "ahead" if s > ego_s else "behind"
    keys = {(li[0], li[1]) for li in ego_route}
    if any((li[0], li[1]) in keys for li in planned_lanes(vehicle)[1:]):
        return "merging"
    ego_approach = approach_of(ego_route[0])
    origin = approach_of(lane)
    if ego_approach is not None and origin is not None and origin == (ego_approach + 2) % 4:
        return "oncoming"
    return "crossing"
