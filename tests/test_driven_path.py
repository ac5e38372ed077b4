"""The AEB shield's driven paths (:class:`av_gym.shields.predict.DrivenPath`): each speed bin's table is highway-env's
route-following controller driven at that speed, step for step. ``_stock_drive`` below is that controller written
with the stock calls (numpy's ufuncs on each float, the position as a 2-vector, highway-env's lanes); the shield's
own loop runs the same formulas through av_gym.sim.fmath and floats, and must give the same numbers bit for bit
(every decision of both stacks reads these tables)."""

from __future__ import annotations

import numpy as np
import pytest

from av_gym.shields.conflicts import ConflictModel
from av_gym.shields.predict import DrivenPath


def _stock_drive(path: DrivenPath, v: float) -> tuple[np.ndarray, ...]:
    """highway-env's ControlledVehicle steering and bicycle step at constant speed ``v``, with numpy's calls."""
    lanes, starts = path.route.lanes, path.route.starts
    k = int(np.clip(np.searchsorted(starts, path.s_start, side="right") - 1, 0, len(lanes) - 1))
    pos = np.array(lanes[k].position(path.s_start - starts[k], 0.0), dtype=float)
    h = float(lanes[k].heading_at(path.s_start - starts[k]))
    d, out = path.s_start, []
    vz = v if abs(v) > 1e-2 else 1e-2
    while True:
        s_l, lat = lanes[k].local_coordinates(pos)
        if s_l > lanes[k].length - path.LANE_SWITCH and k < len(lanes) - 1:
            k += 1
            s_l, lat = lanes[k].local_coordinates(pos)
        s_route = starts[k] + s_l
        out.append((d, pos[0], pos[1], h, s_route))
        if s_route >= path.s_end:
            break
        fut = lanes[k].heading_at(s_l + v * path.TAU_PURSUIT)
        heading_cmd = np.arcsin(np.clip(-path.KP_LATERAL * lat / vz, -1.0, 1.0))
        ref = fut + np.clip(heading_cmd, -np.pi / 4, np.pi / 4)
        rate = path.KP_HEADING * ((ref - h + np.pi) % (2 * np.pi) - np.pi)
        slip = np.arcsin(np.clip(path.LENGTH / 2 / vz * rate, -1.0, 1.0))
        steer = np.clip(np.arctan(2 * np.tan(slip)), -path.MAX_STEERING, path.MAX_STEERING)
        beta = np.arctan(0.5 * np.tan(steer))
        pos = pos + v * path.dt * np.array([np.cos(h + beta), np.sin(h + beta)])
        h += v * np.sin(beta) / (path.LENGTH / 2) * path.dt
        d += v * path.dt
    d, x, y, hh, s = (np.array(c, dtype=float) for c in zip(*out))
    return d, x, y, np.unwrap(hh), s


@pytest.fixture(scope="module")
def paths() -> list[DrivenPath]:
    """Every driven path of the left turn's road network: each lane's continuations (straight approaches and exits,
    the turns' circular lanes, lane switches)."""
    import gymnasium as gym

    import av_gym  # noqa: F401  (registers the envs)

    env = gym.make("av_gym/UnprotectedLeftTurn-v0")
    env.reset(seed=0)
    model = ConflictModel(env.unwrapped.road.network)
    found = {id(p): p for lane_index in env.unwrapped.road.network.lanes_dict()
             for p in model._driven_all(lane_index)}
    env.close()
    return list(found.values())


# m/s: the slowest bin (~2,400 steps a path: ~5 CPU-s of stock drive, slow), a middle one, the fastest
@pytest.mark.parametrize("speed", [pytest.param(0.5, marks=pytest.mark.slow), 3.0, 7.5, 12.0])
def test_the_driven_tables_are_the_stock_controllers_drive(paths, speed):
    assert len(paths) >= 20 and any(len(p.route.lanes) >= 3 for p in paths)
    for path in paths:
        got, ref = path._simulate(speed), _stock_drive(path, speed)
        for column, (a, b) in zip(("distance", "x", "y", "heading", "route position"), zip(got, ref)):
            assert a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64)), \
                f"{column} of the {speed} m/s bin of a path from {path.route.lanes[0]} differs"
