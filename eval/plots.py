"""Lane-keeping figures for ``python -m eval env=lane_keeping``: CTE along the lap (PNG) for each agent and, with
``videos=true``, one lap per agent seen from the centre camera (WebM, VP8: what browsers play; GIF if this OpenCV
has no VP8 encoder). On the left turn ``videos=true`` renders each agent's first episode top-down
(:func:`turn_videos`). Each figure and video is announced by a line before it is drawn (a lap takes seconds).

Each agent drives the first evaluation seed once more with the same sensors and shield as in the
table, so the figure shows one of the laps that were scored (policies are deterministic and sensors are seeded).
Output, in the eval folder: ``cte_<agent>.png`` per agent, ``cte_all.png`` (every agent on one axis) and
``lap_<agent>.webm``. The video is the clean centre-camera render (the same 66×200 view PilotNet drives from,
without sensor noise, scaled ×2; every other frame at 2× real time, about 1.5 MB a lap), with the lap distance
and CTE written on it.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from av_gym.atomic import atomic_path, save_figure_atomic

LANE_UNITS = 100.0  # paper 001: the lane is 100 units wide
VIDEO_SCALE, VIDEO_SPEEDUP, VIDEO_FRAME_STEP = 2, 2, 2  # ×2 size, 2× real time, every other frame (small files)


def record_lap(env, policy, seed: int, video: bool = False, desc: str | None = None) -> dict:
    """Drive one episode; per step: lap distance (m), CTE (m), steering (rad), and centre-camera frames if asked.
    ``desc``: a progress bar of the steps with that title (a lap takes seconds to a minute)."""
    from tqdm import tqdm

    from av_gym.sensors.camera import CameraSpec, render_view
    from eval.runner import single_threaded_torch

    spec = CameraSpec()
    single_threaded_torch()  # as the evaluated lap (eval.runner): the same actions, and no spinning pool
    obs, info = env.reset(seed=int(seed))
    policy.reset()
    trace = {"progress": [], "cte": [], "steering": [], "frames": []}
    done = False
    with tqdm(desc=desc, unit="step", disable=desc is None, leave=False) as bar:
        while not done:
            if video:
                trace["frames"].append(render_view(env, spec))
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            done = terminated or truncated
            for key in ("progress", "cte", "steering"):
                trace[key].append(info["truth"][key])
            bar.update()
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
    ax.set_ylabel("CTE (paper units: lane = 100; + right)")


def cte_title(label: str, title: str, trace: dict) -> str:
    """A lap's CTE figure title: mean |CTE| in metres (SI), then paper 001's units, named (the lane is 100 wide), as
    the axis shows them, so that no bare "units" reads as metres."""
    cte = np.asarray(trace["cte"], dtype=float)
    u = LANE_UNITS * cte / trace["lane_width"]
    lap = "" if trace["lap_completed"] else ", LAP NOT COMPLETED"
    return (f"{label}: {title}\nmean |CTE| {np.abs(cte).mean():.3f} m, max {np.abs(cte).max():.2f} m; paper units "
            f"(lane = 100): mean {np.abs(u).mean():.2f}, std {u.std():.2f}, max {np.abs(u).max():.1f}{lap}")


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
        ax.set_title(cte_title(label, title, tr), fontsize=9)
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
    """The lap's centre-camera frames as a video (:func:`write_frames`) at ``VIDEO_SPEEDUP``× real time."""
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
    """RGB frames (H, W, 3 uint8, all the same size) at ``fps`` as WebM (VP8) at ``path`` with the suffix
    ``.webm``: browsers play it (``mp4v`` MPEG-4 Part 2 they do not, and opencv-python-headless's FFmpeg has no
    H.264 encoder). A GIF (every other frame) where this OpenCV has no VP8 encoder. Written atomically; returns the
    file written."""
    path = Path(path).with_suffix(".webm")
    try:
        with atomic_path(path, "out_dir") as tmp:
            # OpenCV picks the container by the name's suffix: the temporary name must end in .webm too
            named = tmp.with_name(tmp.name + ".webm")
            try:
                _encode_vp8(frames, named, fps)
                named.replace(tmp)
            finally:
                named.unlink(missing_ok=True)
        return path
    except _NoEncoder:
        gif = _write_gif(frames, path.with_suffix(".gif"), fps)
        print(f"[eval] this OpenCV has no VP8 encoder: {gif.name} instead of {path.name}", flush=True)
        return gif


class _NoEncoder(Exception):
    """OpenCV could not open a VP8 writer here."""


def _encode_vp8(frames: list[np.ndarray], path: Path, fps: float) -> None:
    """``frames`` (RGB) into ``path`` with OpenCV's VP8 encoder; :class:`_NoEncoder` if it has none."""
    import cv2

    h, w = frames[0].shape[:2]
    with _quiet_stderr():  # FFmpeg notes that WebM stores no FourCC tag, once per file: true and harmless
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"VP80"), fps, (w, h))
    if not writer.isOpened():
        raise _NoEncoder
    for img in frames:
        writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    writer.release()


def _write_gif(frames: list[np.ndarray], path: Path, fps: float) -> Path:
    """Every other frame as a looping GIF at ``path`` (the fallback: every browser plays it, at ~5x the size)."""
    from PIL import Image

    step = 2
    images = [Image.fromarray(img) for img in frames[::step]]
    with atomic_path(path, "out_dir") as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 * step / fps),
                       loop=0)
    return path


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """File descriptor 2 to /dev/null for the block: FFmpeg writes its notes there from C, past ``sys.stderr``."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def lane_keeping_figures(env_cfg, plans, out_dir: str | Path, first_seed: int, checkpoints: str, split: str,
                         plots: bool = True, videos: bool = False) -> list[Path]:
    """For ``python -m eval``: one more lap per agent plan on ``first_seed`` (the evaluation's first); PNGs and
    optional videos."""
    from eval.agents import make_eval_env, resolve_agent

    traces, paths = {}, []
    drawn = ", ".join(["CTE plot"] * plots + ["video"] * videos)
    for plan in plans:
        print(f"[eval] figures: {plan.label} drives seed {first_seed} once more for its {drawn}", flush=True)
        env = make_eval_env(env_cfg, plan.sensors, plan.shield)
        _, policy = resolve_agent(plan.spec, env, env_cfg["name"], checkpoints)
        traces[plan.label] = record_lap(env, policy, first_seed, video=videos, desc=f"lap of {plan.label}")
        policy_hz = float(env.unwrapped.config["policy_frequency"])
        env.close()
        if videos:
            path = Path(out_dir) / f"lap_{_slug(plan.label)}.webm"
            print(f"[eval] figures: writing {path.name}", flush=True)
            paths.append(write_video(traces[plan.label], plan.label, path, policy_hz))
    if plots:
        title = f"layout {env_cfg.get('track', '?')}, seed {first_seed} ({split})"
        print(f"[eval] figures: drawing {', '.join(f'cte_{_slug(t)}.png' for t in traces)} and cte_all.png",
              flush=True)
        paths += plot_cte(traces, out_dir, title)
    return paths


def turn_videos(env_cfg, plans, out_dir: str | Path, first_seed: int, checkpoints: str) -> list[Path]:
    """For ``python -m eval env=left_turn videos=true``: each agent plan drives ``first_seed`` (the evaluation's
    first) once more with its sensors and shield, rendered top-down by highway-env (the view training's periodic
    GIFs show), at half resolution and real time: ``turn_<agent>.webm``."""
    import cv2

    from eval.agents import make_eval_env, resolve_agent
    from eval.runner import single_threaded_torch

    paths = []
    for plan in plans:
        print(f"[eval] video: {plan.label} drives seed {first_seed} once more, rendered into "
              f"turn_{_slug(plan.label)}.webm", flush=True)
        env = make_eval_env(env_cfg, plan.sensors, plan.shield, render_mode="rgb_array")
        _, policy = resolve_agent(plan.spec, env, env_cfg["name"], checkpoints)
        single_threaded_torch()  # as the evaluated episode (eval.runner): the same actions, and no spinning pool
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
        paths.append(write_frames(frames, Path(out_dir) / f"turn_{_slug(plan.label)}.webm", 1.0 / dt))
    return paths


__all__ = ["record_lap", "plot_cte", "write_video", "write_frames", "lane_keeping_figures", "turn_videos"]
