"""The static roadside world that LiDAR and cameras see: guard rails, poles, sign posts, trees and building fronts.

Generated per episode from the env's ``episode_seed`` along the scenario's own lanes, and kept **out of**
``road.objects``: it is not collidable and costs the simulation nothing (highway-env checks every vehicle against
every object each tick, digest 002 §6.2). Every object keeps a clearance from every lane centreline, so nothing
stands on the road.

Shapes: vertical walls over 2-D segments (guard rails, building fronts) and vertical cylinders over circles
(poles, sign posts, trees), each with a height (m) and a kind (for colours and per-point labels).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import AbstractLane
from scipy.spatial import cKDTree

SEGMENT_KINDS = ("guard_rail", "building")
CIRCLE_KINDS = ("pole", "sign_post", "tree")


@dataclass
class RoadsideWorld:
    """Static scenery in world coordinates (m).

    ``segments`` (M, 4) ``[x0, y0, x1, y1]``, ``segment_height`` (M,), ``segment_kind`` (M,) index into
    :data:`SEGMENT_KINDS`; ``circles`` (K, 3) ``[x, y, radius]``, ``circle_height`` (K,), ``circle_kind`` (K,)
    index into :data:`CIRCLE_KINDS`."""

    segments: np.ndarray
    segment_height: np.ndarray
    segment_kind: np.ndarray
    circles: np.ndarray
    circle_height: np.ndarray
    circle_kind: np.ndarray

    @property
    def size(self) -> int:
        return len(self.segments) + len(self.circles)


# Object dimensions (our choice; typical roadside furniture): heights m, radii m.
GUARD_RAIL_HEIGHT = 0.8
POLE = (0.15, 6.0)
SIGN_POST = (0.08, 2.5)
TREE_RADIUS, TREE_HEIGHT = (0.3, 0.6), (4.0, 8.0)
BUILDING_HEIGHT = (6.0, 15.0)


def _edge_lanes(env) -> tuple[list[AbstractLane], list[AbstractLane]]:
    """(lanes whose right side is a road edge, all lanes) for the scenario."""
    unwrapped = env.unwrapped
    lanes = unwrapped.road.network.lanes_list()
    if unwrapped.scenario == "lane_keeping":
        return list(unwrapped.track.lanes), lanes
    # Intersection arms: the right side of every approach (o→ir) and exit (il→o) lane is the road edge.
    net = unwrapped.road.network
    edge = [net.get_lane((a, b, 0)) for a in net.graph for b in net.graph[a]
            if (a.startswith("o") and b.startswith("ir")) or (a.startswith("il") and b.startswith("o"))]
    return edge, lanes


_TREES: dict[tuple, cKDTree] = {}
"""Centreline trees by road geometry (:func:`geometry_key`): highway-env rebuilds the intersection's road network
every episode, identical each time, and its every-metre centreline sampling was a third of a world's cost."""


def geometry_key(lanes: list[AbstractLane], step: float) -> tuple:
    """Every lane's class and numeric parameters (start, end, centre, radius, phases, length, ...: all that
    ``lane.position`` reads), exactly (as bytes), in order: equal keys give the same centreline points. ``step``
    (or anything else hashable) is part of the key. Also the cameras' key for their road quads."""
    key = [step]
    for lane in lanes:
        key.append(type(lane).__qualname__)
        for name, value in sorted(vars(lane).items()):
            if not name.startswith("_") and isinstance(value, (int, float, np.ndarray, np.number)):
                value = np.asarray(value)
                key.append((name, value.dtype.str, value.shape, value.tobytes()))
    return tuple(key)


def _centreline_tree(lanes: list[AbstractLane], step: float = 1.0) -> cKDTree:
    key = geometry_key(lanes, step)
    tree = _TREES.get(key)
    if tree is None:
        pts = [lane.position(s, 0.0) for lane in lanes for s in np.arange(0.0, lane.length + step, step)]
        tree = cKDTree(np.array(pts))
        if len(_TREES) >= 16:  # a handful of road layouts per process; drop the oldest
            del _TREES[next(iter(_TREES))]
        _TREES[key] = tree
    return tree


def generate_world(env, seed: int) -> RoadsideWorld:
    """Scenery along ``env``'s road, deterministic in ``seed``."""
    rng = np.random.default_rng(seed)
    edge_lanes, all_lanes = _edge_lanes(env)
    width = all_lanes[0].width
    tree = _centreline_tree(all_lanes)
    closed_track = env.unwrapped.scenario == "lane_keeping"
    sides = (1.0, -1.0) if closed_track else (1.0,)  # a lap's lane has road edges on both sides
    segs, seg_h, seg_k, circ, circ_h, circ_k = [], [], [], [], [], []
    # Candidates in generation order: (points that must clear the road or None if already tested, margin m, lists,
    # row, height, kind). Guard rails and roadside furniture draw no random number after their clearance test, so
    # theirs are deferred to one k-d tree query at the end (the same distances, one call instead of thousands); a
    # building draws its height only when it is clear, so it is tested at once.
    candidates: list[tuple[np.ndarray | None, float, tuple[list, list, list], list, float, int]] = []
    seg_lists, circ_lists = (segs, seg_h, seg_k), (circ, circ_h, circ_k)

    def clear(points: np.ndarray, margin: float) -> bool:
        d, _ = tree.query(np.atleast_2d(points))
        return bool(np.all(d >= width / 2 + margin))

    for lane in edge_lanes:
        for side in sides:
            # Guard rail pieces: 1 m beyond the edge line, in 2 m chords (follows curves), with random gaps.
            s = rng.uniform(0, 10)
            while s < lane.length - 2:
                run = rng.uniform(15, 40)
                s_end = min(lane.length, s + run)
                for a in np.arange(s, s_end - 1e-6, 2.0):
                    b = min(a + 2.0, s_end)
                    p0 = lane.position(a, side * (width / 2 + 1.0))
                    p1 = lane.position(b, side * (width / 2 + 1.0))
                    candidates.append(([p0, p1], 0.9, seg_lists, [*p0, *p1], GUARD_RAIL_HEIGHT, 0))
                s = s_end + rng.uniform(10, 40)
            # Poles, sign posts and trees every 8-20 m, 2-6 m beyond the edge line.
            s = rng.uniform(0, 8)
            while s < lane.length:
                kind = rng.choice(3, p=[0.5, 0.2, 0.3])
                p = lane.position(s, side * (width / 2 + rng.uniform(2.0, 6.0)))
                if kind == 0:
                    r, h = POLE
                elif kind == 1:
                    r, h = SIGN_POST
                else:
                    r, h = rng.uniform(*TREE_RADIUS), rng.uniform(*TREE_HEIGHT)
                candidates.append(([p], 1.5 + r, circ_lists, [*p, r], h, int(kind)))
                s += rng.uniform(8, 20)
            # Building fronts 10-25 m off the road, only along straight stretches (facades are straight).
            if lane.heading_at(0.0) == lane.heading_at(lane.length):
                s = rng.uniform(0, 15)
                while s < lane.length - 8:
                    length = rng.uniform(8, 25)
                    off = side * (width / 2 + rng.uniform(10, 25))
                    p0, p1 = lane.position(s, off), lane.position(min(s + length, lane.length), off)
                    mid = np.linspace(p0, p1, 5)
                    if clear(mid, 6.0):
                        candidates.append((None, 0.0, seg_lists, [*p0, *p1], rng.uniform(*BUILDING_HEIGHT), 1))
                    s += length + rng.uniform(5, 25)

    deferred = [c for c in candidates if c[0] is not None]
    owner = np.repeat(np.arange(len(deferred)), [len(c[0]) for c in deferred])
    d, _ = tree.query(np.array([p for c in deferred for p in c[0]], dtype=float).reshape(-1, 2))
    margin = np.array([width / 2 + c[1] for c in deferred])  # clear(): every point at least this far
    blocked = np.bincount(owner, weights=~(d >= margin[owner]), minlength=len(deferred)) > 0
    i = 0
    for points, _, (rows, heights, kinds), row, h, kind in candidates:
        if points is not None:
            i += 1
            if blocked[i - 1]:
                continue
        rows.append(row); heights.append(h); kinds.append(kind)

    def arr(x, cols=None):
        return np.array(x, dtype=float).reshape(-1, cols) if cols else np.array(x)

    return RoadsideWorld(arr(segs, 4), arr(seg_h, None).astype(float), arr(seg_k).astype(int),
                         arr(circ, 3), arr(circ_h).astype(float), arr(circ_k).astype(int))


def roadside_world(env) -> RoadsideWorld:
    """This episode's world for ``env`` (built once per episode and shared by every sensor)."""
    unwrapped = env.unwrapped
    cached = getattr(unwrapped, "_roadside_world", None)
    if cached is None or cached[0] != unwrapped.episode_seed:
        seed = np.random.SeedSequence([unwrapped.episode_seed, 0x57A71C]).generate_state(1)[0]
        unwrapped._roadside_world = (unwrapped.episode_seed, generate_world(unwrapped, int(seed)))
    return unwrapped._roadside_world[1]
