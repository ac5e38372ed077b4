"""Lane geometry of highway-env's ``StraightLane`` and ``CircularLane`` on Python floats, with per-lane cached
parameters: the same formulas, in the same order, as ``highway_env.road.lane``, hence the same bits.

Why: the stock methods build 2-vectors and call numpy on single floats (``np.dot``, ``np.arctan2``,
``np.linalg.norm``) — a few µs per call, and the simulator calls them tens of thousands of times per episode
(closest-lane search, lateral controller, neighbour search). Lanes of any other type, or a platform where
``np.dot`` of 2-vectors is not the plain ``a0*b0 + a1*b1`` (``fmath.DOT_EXACT``), use the stock methods.
"""

from __future__ import annotations

from highway_env.road.lane import AbstractLane, CircularLane, StraightLane

from av_gym.sim import fmath
from av_gym.sim.fmath import atan2, cos, pi, sin, sqrt

STRAIGHT, CIRCULAR, OTHER = 0, 1, 2
_TWO_PI = 2 * pi


def params(lane: AbstractLane) -> tuple:
    """Cached float parameters of a lane (attribute ``_fast_params``; lanes are never mutated after creation)."""
    p = lane.__dict__.get("_fast_params")
    if p is None:
        if type(lane) is StraightLane and fmath.DOT_EXACT:
            p = (STRAIGHT, float(lane.start[0]), float(lane.start[1]), float(lane.direction[0]),
                 float(lane.direction[1]), float(lane.direction_lateral[0]), float(lane.direction_lateral[1]),
                 lane.length, lane.heading)
        elif type(lane) is CircularLane and fmath.DOT_EXACT:
            p = (CIRCULAR, float(lane.center[0]), float(lane.center[1]), lane.radius, lane.start_phase,
                 lane.direction, lane.length)
        else:
            p = (OTHER,)
        lane._fast_params = p
    return p


def local_coordinates(lane: AbstractLane, x: float, y: float) -> tuple[float, float]:
    """``lane.local_coordinates(np.array([x, y]))``."""
    p = lane.__dict__.get("_fast_params") or params(lane)
    kind = p[0]
    if kind == STRAIGHT:
        dx, dy = x - p[1], y - p[2]
        return dx * p[3] + dy * p[4], dx * p[5] + dy * p[6]
    if kind == CIRCULAR:
        dx, dy = x - p[1], y - p[2]
        phase, direction, radius = p[4], p[5], p[3]
        phi = atan2(dy, dx)
        phi = phase + (((phi - phase + pi) % _TWO_PI) - pi)
        r = sqrt(dx * dx + dy * dy)
        return direction * (phi - phase) * radius, direction * (radius - r)
    import numpy as np

    s, r = lane.local_coordinates(np.array([x, y]))
    return s, r


def heading_at(lane: AbstractLane, s: float) -> float:
    """``lane.heading_at(s)``."""
    p = lane.__dict__.get("_fast_params") or params(lane)
    kind = p[0]
    if kind == STRAIGHT:
        return p[8]
    if kind == CIRCULAR:
        direction = p[5]
        return direction * s / p[3] + p[4] + pi / 2 * direction
    return lane.heading_at(s)


def position(lane: AbstractLane, s: float, lateral: float) -> tuple[float, float]:
    """``lane.position(s, lateral)`` as two floats."""
    p = lane.__dict__.get("_fast_params") or params(lane)
    kind = p[0]
    if kind == STRAIGHT:
        return p[1] + s * p[3] + lateral * p[5], p[2] + s * p[4] + lateral * p[6]
    if kind == CIRCULAR:
        direction, radius = p[5], p[3]
        phi = direction * s / radius + p[4]
        k = radius - lateral * direction
        return p[1] + k * cos(phi), p[2] + k * sin(phi)
    xy = lane.position(s, lateral)
    return float(xy[0]), float(xy[1])


def distance_with_heading(lane: AbstractLane, x: float, y: float, heading) -> float:
    """``lane.distance_with_heading(np.array([x, y]), heading)`` (``heading`` may be None)."""
    p = lane.__dict__.get("_fast_params") or params(lane)
    if p[0] == OTHER:
        import numpy as np

        return lane.distance_with_heading(np.array([x, y]), heading)
    s, r = local_coordinates(lane, x, y)
    length = p[7] if p[0] == STRAIGHT else p[6]
    d = abs(r) + max(s - length, 0) + max(0 - s, 0)
    if heading is None:
        return d
    angle = abs(((heading - heading_at(lane, s) + pi) % _TWO_PI) - pi)
    return d + 1.0 * angle


def locate(path, x: float, y: float, hint: int) -> tuple[int, float, float]:
    """``av_gym.envs.lane_path.LanePath.locate(np.array([x, y]), hint)`` with :func:`local_coordinates` (the same
    walk from the hint lane, the same floats)."""
    lanes = path.lanes
    n = len(lanes)
    k = hint
    s, lat = local_coordinates(lanes[k], x, y)
    step = 1 if s > lanes[k].length else -1 if s < 0 else 0
    for _ in range(n if step else 0):
        nxt = k + step
        if not path.closed and not 0 <= nxt < n:
            break
        k = nxt % n
        s, lat = local_coordinates(lanes[k], x, y)
        if (step > 0 and s <= lanes[k].length) or (step < 0 and s >= 0):
            break
    return k, float(s), float(lat)
