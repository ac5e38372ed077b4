"""Lane-keeping figures for ``python -m eval env=lane_keeping``: CTE along the lap (PNG) for each agent and, with
``videos=true``, one lap per agent seen from the centre camera (MP4, or GIF if no MP4 encoder is available). On the
left turn ``videos=true`` renders each agent's first episode top-down (:func:`turn_videos`).

Each agent drives the first evaluation seed once more with the same sensors and shield as in the
table, so the figure shows one of the laps that were scored (policies are deterministic and sensors are seeded).
Output, in the eval folder: ``cte_<agent>.png`` per agent, ``cte_all.png`` (every agent on one axis) and
``lap_<agent>.mp4``. The video is the clean centre-camera render (the same 66×200 view PilotNet drives from,
without sensor noise, scaled ×2; every other frame at 2× real time, about 1.5 MB a lap), with the lap distance
and CTE written on it.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from av_gym.atomic import save_figure_atomic

LANE_UNITS = 100.0  # paper 001: the lane is 100 units wide
VIDEO_SCALE, VIDEO_SPEEDUP, VIDEO_FRAME_STEP = 2, 2, 2  # ×2 size, 2× real time, every other frame (small files)


def record_lap(env, policy, seed: int, video: bool = False) -> dict:
    """Drive one episode; per step: lap distance (m), CTE (m), steering (rad), and centre-camera frames if asked."""
    from av_gym.sensors.camera import CameraSpec, render_view

    spec = CameraSpec()
    obs, info = env.reset(seed=int(seed))
    policy.reset()
    trace = {"progress": [], "cte": [], "steering": [], "frames": []}
    done = False
    while not done:
        if video:
            trace["frames"].append(render_view(env, spec))
        obs, _, terminated, truncated, info = env.step(policy.act(obs))
        done = terminated or truncated
        for key in ("progress", "cte", "steering"):
            trace[key].append(info["truth"][key])
    out = {k: np.asarray(v, dtype=float) for k, v in trace.items() if k != "frames"}
    out["frames"] = trace["frames"]
    out["lane_width"] = float(info["truth"]["lane_width"])
    out["vehicle_width"] = float(info["truth"]["vehicle_width"])
    out["lap_completed"] = bool(info["truth"]["lap_completed"])
    out["curvature"] = env.unwrapped.track.curvature(np.mod(out["progress"], env.unwrapped.track.length))
    return out


def _slug(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(label).name or label).strip("_") or "agent"


def _axes_for_lap(ax, trace: dict) -> None:
    """Lane lines, the wheel-on-the-line threshold and shaded curves (blue = left turn, red = right turn)."""
    half = LANE_UNITS / 2
    wheel = LANE_UNITS * (trace["lane_width"] - trace["vehicle_width"]) / 2 / trace["lane_width"]
    x, k = trace["progress"], trace["curvature"]
    for sign, colour in ((-1, "tab:blue"), (1, "tab:red")):
        on = np.sign(k) == sign
        edges = np.flatnonzero(np.diff(np.r_[0, on.astype(int), 0]))
        for a, b in zip(edges[::2], edges[1::2]):
            ax.axvspan(x[a], x[min(b, len(x) - 1)], color=colour, alpha=0.08, lw=0)
    for y in (-half, half):
        ax.axhline(y, color="k", lw=1)
    for y in (-wheel, wheel):
        ax.axhline(y, color="k", lw=0.6, ls=":")
    ax.axhline(0, color="grey", lw=0.6)
    ax.set_ylim(-half - 5, half + 5)
    ax.set_xlabel("distance along the lap (m)")
    ax.set_ylabel("CTE (units, lane = 100; + right)")


def plot_cte(traces: dict[str, dict], out_dir: str | Path, title: str) -> list[Path]:
    """``cte_<agent>.png`` for each agent and ``cte_all.png``; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for label, tr in traces.items():
        u = LANE_UNITS * tr["cte"] / tr["lane_width"]
        fig, ax = plt.subplots(figsize=(9, 3.2))
        _axes_for_lap(ax, tr)
        ax.plot(tr["progress"], u, lw=1.2, color="tab:green")
        ax.set_title(f"{label}: {title}\nmean |CTE| {np.abs(u).mean():.2f} units, std {u.std():.2f}, "
                     f"max {np.abs(u).max():.1f}{'' if tr['lap_completed'] else ', LAP NOT COMPLETED'}", fontsize=9)
        fig.tight_layout()
        paths.append(out_dir / f"cte_{_slug(label)}.png")
        save_figure_atomic(fig, paths[-1], "out_dir", dpi=110)  # whole or as it was
        plt.close(fig)
    fig, ax = plt.subplots(figsize=(9, 3.6))
    first = next(iter(traces.values()))
    _axes_for_lap(ax, first)
    for label, tr in traces.items():
        u = LANE_UNITS * tr["cte"] / tr["lane_width"]
        ax.plot(tr["progress"], u, lw=1.0, label=f"{label} (mean |CTE| {np.abs(u).mean():.2f})")
    peak = max(float(np.abs(LANE_UNITS * tr["cte"] / tr["lane_width"]).max()) for tr in traces.values())
    lim = min(LANE_UNITS / 2 + 5, max(10.0, 1.25 * peak))  # zoom in when every agent stays near the centre
    ax.set_ylim(-lim, lim)
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title(f"CTE along the lap: {title} (shaded: blue left turn, red right turn; dotted: a wheel on the "
                 f"line)", fontsize=9)
    fig.tight_layout()
    paths.append(out_dir / "cte_all.png")
    save_figure_atomic(fig, paths[-1], "out_dir", dpi=110)
    plt.close(fig)
    return paths


def write_video(trace: dict, label: str, path: str | Path, policy_hz: float = 10.0) -> Path:
    """The lap's centre-camera frames as MP4 (``mp4v``) at ``VIDEO_SPEEDUP``× real time; GIF if MP4 fails."""
    import cv2

    frames = trace["frames"]
    if not frames:
        raise ValueError("no frames recorded (record_lap(..., video=True))")
    h, w = frames[0].shape[:2]
    size = (w * VIDEO_SCALE, h * VIDEO_SCALE)
    out = []
    for i in range(0, len(frames), VIDEO_FRAME_STEP):
        f = frames[i]
        img = cv2.resize(f, size, interpolation=cv2.INTER_NEAREST)
        u = LANE_UNITS * trace["cte"][i] / trace["lane_width"]
        text = f"{label}  {trace['progress'][i]:5.0f} m  CTE {u:+5.1f}"
        cv2.putText(img, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        out.append(img)
    return write_frames(out, path, policy_hz * VIDEO_SPEEDUP / VIDEO_FRAME_STEP)


def write_frames(frames: list[np.ndarray], path: str | Path, fps: float) -> Path:
    """RGB frames (H, W, 3 uint8, all the same size) as MP4 (``mp4v``) at ``fps``; a GIF beside it (every other
    frame) if OpenCV has no MP4 encoder here. Returns the file written."""
    import cv2

    path = Path(path)
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if writer.isOpened():
        for img in frames:
            writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        writer.release()
        return path
    from PIL import Image

    gif = path.with_suffix(".gif")
    step = 2  # every other written frame again keeps the GIF small
    images = [Image.fromarray(img) for img in frames[::step]]
    images[0].save(gif, save_all=True, append_images=images[1:], duration=int(1000 * step / fps), loop=0)
    return gif


def lane_keeping_figures(env_cfg, plans, out_dir: str | Path, first_seed: int, checkpoints: str, split: str,
                         plots: bool = True, videos: bool = False) -> list[Path]:
    """For ``python -m eval``: one more lap per agent plan on ``first_seed`` (the evaluation's first); PNGs and
    optional videos."""
    from eval.agents import make_eval_env, resolve_agent

    traces, paths = {}, []
    for plan in plans:
        env = make_eval_env(env_cfg, plan.sensors, plan.shield)
        _, policy = resolve_agent(plan.spec, env, env_cfg["name"], checkpoints)
        traces[plan.label] = record_lap(env, policy, first_seed, video=videos)
        policy_hz = float(env.unwrapped.config["policy_frequency"])
        env.close()
        if videos:
            paths.append(write_video(traces[plan.label], plan.label, Path(out_dir) / f"lap_{_slug(plan.label)}.mp4",
                                     policy_hz))
    if plots:
        title = f"layout {env_cfg.get('track', '?')}, seed {first_seed} ({split})"
        paths += plot_cte(traces, out_dir, title)
    return paths


def turn_videos(env_cfg, plans, out_dir: str | Path, first_seed: int, checkpoints: str) -> list[Path]:
    """For ``python -m eval env=left_turn videos=true``: each agent plan drives ``first_seed`` (the evaluation's
    first) once more with its sensors and shield, rendered top-down by highway-env (the view training's periodic
    GIFs show), at half resolution and real time: ``turn_<agent>.mp4``."""
    import cv2

    from eval.agents import make_eval_env, resolve_agent

    paths = []
    for plan in plans:
        env = make_eval_env(env_cfg, plan.sensors, plan.shield, render_mode="rgb_array")
        _, policy = resolve_agent(plan.spec, env, env_cfg["name"], checkpoints)
        obs, _ = env.reset(seed=int(first_seed))
        policy.reset()
        frames, done, t = [], False, 0.0
        dt = 1.0 / float(env.unwrapped.config["policy_frequency"])
        while True:
            img = np.ascontiguousarray(env.render()[::2, ::2])
            text = f"{plan.label}  t {t:4.1f} s"
            cv2.putText(img, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(img, text, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
            frames.append(img)
            if done:
                break
            obs, _, terminated, truncated, _ = env.step(policy.act(obs))
            done, t = terminated or truncated, t + dt
        env.close()
        paths.append(write_frames(frames, Path(out_dir) / f"turn_{_slug(plan.label)}.mp4", 1.0 / dt))
    return paths


__all__ = ["record_lap", "plot_cte", "write_video", "write_frames", "lane_keeping_figures", "turn_videos"]
