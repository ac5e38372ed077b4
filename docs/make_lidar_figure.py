"""Plot one LiDAR scan over its scene, seen from above, for both scenarios.

    python docs/make_lidar_figure.py [--out docs]

writes ``lidar_scans.png`` (lane keeping on the left, the left turn on the right) into ``--out`` (default: docs/,
beside this script). Lanes, the roadside world (guard rails, building fronts, poles, sign posts, trees), the other vehicles and
the ego are drawn in highway-env's world frame with the y axis pointing down, as on highway-env's screen; the scan's
points are mapped back to that frame with the true scan pose and coloured by label (static world / vehicle).
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Polygon  # noqa: E402

import av_gym  # noqa: E402,F401  (registers the envs)
from agents.pid import PIDSteering  # noqa: E402
from av_gym.atomic import save_figure_atomic  # noqa: E402
from av_gym.geometry import box_corners  # noqa: E402
from av_gym.sensors.base import others_state  # noqa: E402
from av_gym.sensors.lidar import LABEL_VEHICLE, Lidar, sensor_to_world  # noqa: E402
from av_gym.sensors.world import CIRCLE_KINDS, roadside_world  # noqa: E402
from conf.cli import ToolParser  # noqa: E402

OUT = Path(__file__).resolve().parent
CIRCLE_COLOURS = {"pole": "0.2", "sign_post": "tab:orange", "tree": "tab:green"}


def draw_scene(ax, env: gym.Env) -> None:
    """Lanes (edges solid, centrelines dashed), roadside world and vehicles, in world coordinates (m)."""
    unwrapped = env.unwrapped
    for lane in unwrapped.road.network.lanes_list():
        s = np.linspace(0.0, lane.length, max(2, int(lane.length)))
        for lat, style in ((-lane.width / 2, "-"), (lane.width / 2, "-"), (0.0, "--")):
            xy = np.array([lane.position(si, lat) for si in s])
            ax.plot(xy[:, 0], xy[:, 1], style, color="0.75", lw=0.6, zorder=1)
    world = roadside_world(env)
    for (x0, y0, x1, y1), kind in zip(world.segments, world.segment_kind):
        ax.plot([x0, x1], [y0, y1], color="0.45" if kind == 0 else "tab:brown", lw=1.2 if kind == 0 else 2.5,
                solid_capstyle="butt", zorder=2)
    for (x, y, r), kind in zip(world.circles, world.circle_kind):
        ax.add_patch(Circle((x, y), r, color=CIRCLE_COLOURS[CIRCLE_KINDS[kind]], zorder=2))
    others = others_state(env)
    for corners in box_corners(others[:, 0:2], others[:, 4], others[:, 5], others[:, 6]):
        ax.add_patch(Polygon(corners, closed=True, fc="none", ec="tab:red", lw=1.0, zorder=3))
    ego = unwrapped.vehicle
    ax.add_patch(Polygon(box_corners(ego.position, ego.heading, ego.LENGTH, ego.WIDTH), closed=True,
                         fc="tab:blue", ec="k", alpha=0.6, lw=1.0, zorder=3))


def plot_scan(ax, env: Lidar, title: str, half_width: float = 60.0) -> None:
    points, _ = env.points()
    labels = env.labels()
    pose = env.scan_pose()
    xy = sensor_to_world(points, pose)
    draw_scene(ax, env)
    static = labels != LABEL_VEHICLE
    ax.scatter(xy[static, 0], xy[static, 1], s=3, c="tab:cyan", label=f"static returns ({static.sum()})", zorder=4)
    ax.scatter(xy[~static, 0], xy[~static, 1], s=5, c="magenta", label=f"vehicle returns ({(~static).sum()})",
               zorder=5)
    ax.plot(*pose[0:2], "k+", ms=10, zorder=6, label="sensor")
    ax.arrow(pose[0], pose[1], 6 * np.cos(pose[2]), 6 * np.sin(pose[2]), width=0.3, color="k", zorder=6)
    ax.set_xlim(pose[0] - half_width, pose[0] + half_width)
    ax.set_ylim(pose[1] + half_width, pose[1] - half_width)  # y down, like highway-env's screen
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m, down as on highway-env's screen)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)


def main() -> None:
    parser = ToolParser(prog="docs/make_lidar_figure.py", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT, help="folder for the figure (default: docs/)")
    out = parser.parse_args().out
    out.mkdir(parents=True, exist_ok=True)
    fig, (left, right) = plt.subplots(1, 2, figsize=(16, 8))
    # Lane keeping: a few seconds into the lap, entering the first hairpin (guard rails, poles and buildings).
    env = Lidar(gym.make("av_gym/LaneKeepingLap-v0"))
    obs, _ = env.reset(seed=3)
    pid = PIDSteering()
    for _ in range(100):
        obs, _, terminated, truncated, _ = env.step(pid.act(obs))
        assert not (terminated or truncated)
    plot_scan(left, env, "LaneKeepingLap-v0: one 720-beam planar LiDAR scan (seed 3, t = 10 s)")

    # Left turn: ego at the stop line with cross and oncoming traffic around.
    env = Lidar(gym.make("av_gym/UnprotectedLeftTurn-v0"))
    env.reset(seed=5)
    for _ in range(25):
        _, _, terminated, truncated, _ = env.step(1)
        assert not (terminated or truncated)
    plot_scan(right, env, "UnprotectedLeftTurn-v0: one 720-beam planar LiDAR scan (seed 5, t = 2.5 s)")
    fig.tight_layout()
    save_figure_atomic(fig, out / "lidar_scans.png", "--out", dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
