"""Closed-circuit track layouts for the lane-keeping lap, built from highway-env lanes.

A layout is a list of segments driven in order from the start line: straights and circular arcs. Arc angles are
signed in the *driver's* sense: positive = right turn. In highway-env's frame (x right, y down on screen) a right
turn is an increasing heading and a clockwise ``CircularLane``.

Two straights per layout are marked as *closure* straights: their lengths are solved so that the circuit ends
exactly where it started (a 2×2 linear system), so layouts can be written from intent ("150 m straight, then a
25 m-radius hairpin") without hand-computing coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, LineType, StraightLane
from highway_env.road.road import RoadNetwork

from av_gym.envs.lane_path import LanePath


@dataclass(frozen=True)
class Segment:
    """One piece of the centreline. ``kind`` is "straight" (``length`` m) or "arc" (``radius`` m, ``angle`` deg,
    + = right turn). ``closure`` straights get their length solved (``length`` is then ignored)."""

    kind: str
    length: float = 0.0
    radius: float = 0.0
    angle: float = 0.0
    closure: bool = False


def S(length: float) -> Segment:
    return Segment("straight", length=length)


def C() -> Segment:
    return Segment("straight", closure=True)


def R(radius: float, angle_deg: float) -> Segment:
    return Segment("arc", radius=radius, angle=angle_deg)


# Layout "A" (training layout): a 120 m straight into a 25 m-radius left hairpin (paper 001's "sharp
# curve after the bridge"), a right-left S-bend, a 30 m left, and two wide closing lefts. Layout "B" (held-out
# layout for evaluation): driven the other way round with different radii, so its sharpest curve (22 m) is a
# *right* turn and its S-bend is left-right; a network trained on A has never seen it.
LAYOUTS: dict[str, list[Segment]] = {
    "A": [S(120), R(25, -90), S(40), R(30, 60), R(30, -60), S(20), R(30, -90), C(), R(40, -90), C(), R(40, -90)],
    "B": [S(100), R(22, 90), S(30), R(30, -45), R(30, 45), S(30), R(40, 90), C(), R(25, -60), R(25, 60),
          R(45, 90), C(), R(35, 90)],
}


@dataclass
class Track(LanePath):
    """A built circuit: a closed :class:`LanePath` plus its name, lane width and highway-env road network."""

    name: str = "A"
    lane_width: float = AbstractLane.DEFAULT_WIDTH
    network: RoadNetwork | None = None
    lane_indices: list[tuple[str, str, int]] | None = None


def _advance(p: np.ndarray, psi: float, seg: Segment, length: float) -> tuple[np.ndarray, float]:
    if seg.kind == "straight":
        return p + length * np.array([np.cos(psi), np.sin(psi)]), psi
    theta = np.radians(seg.angle)
    direction = 1 if theta > 0 else -1
    phi0 = psi - direction * np.pi / 2
    center = p - seg.radius * np.array([np.cos(phi0), np.sin(phi0)])
    phi1 = phi0 + theta
    return center + seg.radius * np.array([np.cos(phi1), np.sin(phi1)]), psi + theta


def _solve_closure(segments: list[Segment]) -> list[float]:
    """Lengths of every segment, with the two closure straights solved so the lap closes (m)."""
    closure_idx = [i for i, seg in enumerate(segments) if seg.closure]
    if len(closure_idx) != 2:
        raise ValueError(f"a layout needs exactly 2 closure straights, got {len(closure_idx)}")
    total_turn = sum(seg.angle for seg in segments if seg.kind == "arc")
    if not np.isclose(abs(total_turn), 360.0):
        raise ValueError(f"a closed layout must turn ±360 deg in total, this one turns {total_turn} deg")
    lengths = [seg.length for seg in segments]
    p, psi = np.zeros(2), 0.0
    headings = {}
    for i, seg in enumerate(segments):
        if seg.closure:
            headings[i] = psi
            continue
        p, psi = _advance(p, psi, seg, lengths[i])
    a, b = closure_idx
    A = np.array([[np.cos(headings[a]), np.cos(headings[b])], [np.sin(headings[a]), np.sin(headings[b])]])
    la, lb = np.linalg.solve(A, -p)
    if la < 5.0 or lb < 5.0:
        raise ValueError(f"layout does not close with positive straights (solved {la:.1f} m, {lb:.1f} m)")
    lengths[a], lengths[b] = float(la), float(lb)
    return lengths


def build_track(name: str = "A", lane_width: float = AbstractLane.DEFAULT_WIDTH, speed_limit: float = 30.0) -> Track:
    """Build layout ``name`` as a highway-env ``RoadNetwork`` (one lane, continuous edge lines both sides)."""
    if name not in LAYOUTS:
        raise ValueError(f"track must be one of {sorted(LAYOUTS)}, got {name!r}")
    segments = LAYOUTS[name]
    lengths = _solve_closure(segments)
    net = RoadNetwork()
    c = LineType.CONTINUOUS
    lanes, indices = [], []
    p, psi = np.zeros(2), 0.0
    n = len(segments)
    for i, (seg, length) in enumerate(zip(segments, lengths)):
        if seg.kind == "straight":
            end, psi_end = _advance(p, psi, seg, length)
            lane = StraightLane(p, end, width=lane_width, line_types=(c, c), speed_limit=speed_limit)
        else:
            theta = np.radians(seg.angle)
            direction = 1 if theta > 0 else -1
            phi0 = psi - direction * np.pi / 2
            center = p - seg.radius * np.array([np.cos(phi0), np.sin(phi0)])
            lane = CircularLane(center, seg.radius, phi0, phi0 + theta, clockwise=direction > 0,
                                width=lane_width, line_types=(c, c), speed_limit=speed_limit)
            end, psi_end = _advance(p, psi, seg, length)
        index = (f"t{i}", f"t{(i + 1) % n}", 0)
        net.add_lane(index[0], index[1], lane)
        lanes.append(lane)
        indices.append(index)
        p, psi = end, psi_end
    if np.linalg.norm(p) > 1e-6:
        raise AssertionError(f"track {name} does not close: ends at {p}")
    return Track(lanes, closed=True, name=name, lane_width=lane_width, network=net, lane_indices=indices)
