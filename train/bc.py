"""Behaviour cloning of PilotNet from three cameras, top to bottom (CleanRL style): arguments → expert →
demonstrations on disk → balancing → augmentation → training loop with TensorBoard, early stopping and an atomic
best checkpoint; :func:`train_pilotnet` is the trainer ``python -m train agent=pilotnet`` calls (it reads the Hydra
config). The settings are :class:`agents.bc.PilotNetParams` (``conf/agent/pilotnet.yaml``'s defaults); the network,
its preprocessing and the driving policy are :mod:`agents.pilotnet`.

Paper 001 cloned a human driver in the Udacity simulator; here the demonstrator is a scripted expert that sees the
truth (digest 001 §8.5): **pure pursuit on the lane centreline**, deliberately not the PID that PilotNet is compared
with (otherwise the comparison would be circular).

Expert (slip-compensated pure pursuit for highway-env's kinematic bicycle)
    The target point T lies ``lookahead`` metres further along the lane centreline than the car's projection onto
    it. highway-env's ``Vehicle`` moves its centre point (the reference of the CTE) in the direction heading + β,
    with slip angle β = atan(tan δ / 2), on a path of curvature sin β / (L/2), L = 5 m. With α the angle from that
    velocity direction to T and ℓ = |T − p|, the circle through the car tangent to its velocity has curvature
    κ = 2 sin α / ℓ, so the wheel angle is δ = atan(2 tan(asin(κ L/2))) and the normalised command u = δ / 25°
    (clipped to [−1, 1]). The β used in α is the steady-state slip of the *map* curvature averaged over the
    lookahead, β̄ = asin(κ̄ L/2) (feed-forward; using the car's current steering instead closes a loop that
    oscillates at 10 Hz). Without it plain pure pursuit cuts every curve by about 2β/ℓ of curvature: with a 4 m
    lookahead it drives A at 2.6 units mean |CTE| and B at 3.3; with it, at the default 6 m lookahead, 0.44 and 0.55
    (max 1.5 / 1.7), against 4.9 / 6.1 for the paper PID (2 seeds each).

Demonstrations (digest 001 §8.5 step 2)
    Laps of the training layout on train-split seeds (``demo_seed`` + i, av_gym/seeds.py; others are refused);
    evaluations use the validation and test splits. The executed steering is the expert's command plus an Ornstein–Uhlenbeck
    perturbation (σ ``perturb_std``, correlation time ``perturb_tau``), so the car drifts off the centre and the
    data contains recoveries; the *label* is always the clean expert command. All three cameras are recorded every
    step, rendered without sensor noise (noise is re-created by augmentation, fresh every epoch; clean renders
    also compress well, about 2.2 kB per image in ``np.savez_compressed``).

Side-camera labels
    A side camera at lateral offset d (left −0.6 m, right +0.6 m) sees exactly what the centre camera would see if
    the car stood d to that side with the same heading. ``side_labels: expert`` (default) labels the image with the
    expert's command evaluated at that displaced pose, ``u(x + d·r̂, ψ)`` with r̂ the right-hand unit vector. For a
    car on a straight this is the pure-pursuit recovery over the lookahead, u ≈ atan(2·L·d/ℓ²)/25° with
    L = 5 m: +0.38 for the left camera at d = 0.6 m and a 6 m lookahead (a recovery over ``lookahead`` metres), and
    on curves it includes the curvature. ``side_labels: geometric`` instead adds the folk constant
    c = ± atan(d / recovery_distance) / 25° to the centre label (+ for the left camera: the left camera sees the
    car as if it were left of centre, so its label steers right, + = right); at d = 0.6 m and 10 m this is ±0.137.

Balancing, preprocessing, augmentation (digest 001 §8.5 steps 4–6)
    Balancing: 25-bin histogram of the labels over [−1, 1]; bins holding more than ``bin_cap`` samples
    (default ``cap_factor`` × the median non-empty bin) are subsampled to the cap (paper 001: "clipped according to
    a certain threshold"). Applied to the training split only. Preprocessing: :mod:`agents.pilotnet` (crop the sky,
    YUV, normalise). Augmentation per sample and epoch, in this order: horizontal flip with the label negated
    (probability ``flip_p``); horizontal shift of ±``shift_px`` px, read as a yaw of the camera by
    Δψ = −atan(tx / f) (f the focal length in px; content moving right = camera turned left), with the label
    corrected by the expert's own sensitivity, u += (∂u/∂ψ)·Δψ, ∂u/∂ψ measured per sample by finite differences at
    collection time; a vertical shift of ±``vshift_px`` px and a roll of ±``rotate_deg`` (label unchanged: the
    road ahead does not change with a small pitch or roll); brightness offset, contrast and gain per image and
    Gaussian pixel noise, wider than the evaluation camera's noise (``CameraNoise`` in av_gym/sensors/camera.py).

Training (digest 001 §3.3, §8.5 step 7): Adam, lr 1e-3, batch 100, MSE on the normalised steering; validation on
``val_fraction`` of the data split by contiguous ``val_chunk_s``-second pieces of driving (all cameras of a frame
on the same side; neighbouring frames are near duplicates, so a per-frame split would leak); early stopping after
``patience`` epochs without a better validation loss; the best model is written atomically to ``model.pt``.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf

from agents.bc import PilotNetParams
from agents.pilotnet import (FORMAT, INPUT_HEIGHT, INPUT_WIDTH, PilotNet, count_parameters, crop_resize,
                             to_network_input)
from agents.registry import AgentParams
from av_gym.atomic import atomic_path
from av_gym.geometry import wrap_angle
from conf.commands import TrainCommand
from train.device import device_problems, resolve_device

CAMERAS = ("left", "centre", "right")
DEMO_VERSION = 1


# ================================================================================================ 2. the expert
class PurePursuitExpert:
    """Pure pursuit on the centreline of ``track`` (an :class:`av_gym.envs.track.Track`); see the module docstring."""

    def __init__(self, track: Any, lookahead: float, max_steering: float, vehicle_length: float = 5.0) -> None:
        self.track, self.lookahead, self.max_steering = track, float(lookahead), float(max_steering)
        self.half_length = vehicle_length / 2

    def centreline(self, lap_s: float) -> np.ndarray:
        """Centreline point (m) at lap position ``lap_s`` (m, wrapped)."""
        t = self.track
        s = float(lap_s) % t.length
        k = int(np.clip(np.searchsorted(t.starts, s, side="right") - 1, 0, len(t.lanes) - 1))
        return np.asarray(t.lanes[k].position(s - t.starts[k], 0.0), dtype=float)

    def command(self, x: float, y: float, heading: float, hint: int) -> tuple[float, int]:
        """Normalised steering for a car at ``(x, y, heading)``; ``hint`` is the lane index it was last on.
        Returns ``(u, lane index)``."""
        p = np.array([x, y], dtype=float)
        k, s, _ = self.track.locate(p, hint)
        lap_s = self.track.starts[k] + s
        target = self.centreline(lap_s + self.lookahead)
        d = target - p
        dist = max(float(np.hypot(d[0], d[1])), 1e-6)
        # Slip compensation: aim the velocity (heading + β), not the body, with β the steady-state slip for the
        # mean map curvature over the lookahead (feed-forward from the map: no loop through the current steering).
        kappa_map = float(np.mean(self.track.curvature(lap_s + np.linspace(0.0, self.lookahead, 9))))
        beta = math.asin(float(np.clip(kappa_map * self.half_length, -0.999, 0.999)))
        alpha = math.atan2(d[1], d[0]) - heading - beta
        alpha = wrap_angle(alpha)
        kappa = 2.0 * math.sin(alpha) / dist
        sin_beta = float(np.clip(kappa * self.half_length, -0.999, 0.999))
        delta = math.atan(2.0 * math.tan(math.asin(sin_beta)))
        return float(np.clip(delta / self.max_steering, -1.0, 1.0)), k

    def labels(self, x: float, y: float, heading: float, hint: int, offsets: dict[str, float],
               h: float = 0.02) -> tuple[dict[str, float], dict[str, float], int]:
        """Per camera: the command at the pose displaced by the camera's lateral offset (m, + = right), and its
        derivative with respect to the heading (per rad, central difference ±``h``). Also the car's lane index."""
        right = np.array([-math.sin(heading), math.cos(heading)])
        u, du, k0 = {}, {}, hint
        for name, off in offsets.items():
            px, py = np.array([x, y]) + off * right
            u[name], k = self.command(px, py, heading, hint)
            if off == 0.0:
                k0 = k
            du[name] = (self.command(px, py, heading + h, hint)[0] - self.command(px, py, heading - h, hint)[0]) / (2 * h)
        return u, du, k0


def geometric_side_label(u_centre: float, offset: float, recovery_distance: float, max_steering: float) -> float:
    """The folk side-camera label: ``u_centre − sign(offset)·atan(|offset| / recovery_distance) / max_steering``
    (a camera on the left, offset < 0, gets a label steering right, i.e. larger)."""
    c = math.atan(abs(offset) / recovery_distance) / max_steering
    return float(np.clip(u_centre - math.copysign(c, offset), -1.0, 1.0))


# ================================================================================================ 3. demonstrations
def demo_cte_text(metrics: dict) -> str:
    """A demo lap's mean |CTE| for the log: metres (SI, ``cte_mean_abs_m``), with paper 001's units beside it,
    named (the lane is 100 units wide: av_gym/metrics/lane_keeping.py), so that no bare "units" is read as m."""
    nan = float("nan")
    return (f"mean |CTE| {metrics.get('cte_mean_abs_m', nan):.3f} m "
            f"({metrics.get('cte_mean_abs_units', nan):.1f} paper units, lane = 100)")


def collect_demos(env_cfg: dict, sensors_cfg: dict, args: PilotNetParams, log: Callable[[str], None] = print) -> dict:
    """Drive ``args.demo_laps`` perturbed expert laps with the camera rig; returns the demo arrays (see
    :func:`save_demos`). Images are clean renders: the sensors preset's camera noise is switched off here."""
    from av_gym.make import make_env

    sensors_cfg = json.loads(json.dumps(sensors_cfg))  # a plain deep copy
    if "cameras" not in sensors_cfg:
        raise ValueError("demonstrations need a sensors preset with cameras")
    sensors_cfg["cameras"]["noise"] = None  # clean renders
    env = make_env(env_cfg, sensors_cfg)
    u_env = env.unwrapped
    cam = env.get_wrapper_attr("specs")
    offsets = {name: float(cam[name].lateral_offset) for name in CAMERAS}
    max_steering = float(u_env.config["max_steering"])
    dt = 1.0 / float(u_env.config["policy_frequency"])
    rng = np.random.default_rng(_seed(args) + 7919)
    rows: dict[str, list] = {k: [] for k in ("images", "steering", "dsteer_dyaw", "camera", "frame", "lap", "seed",
                                            "cte", "heading_error", "progress")}
    frame, t0 = 0, time.time()
    for lap in range(args.demo_laps):
        seed = args.demo_seed + lap
        obs, info = env.reset(seed=seed)
        expert = PurePursuitExpert(u_env.track, args.lookahead, max_steering, u_env.vehicle.LENGTH)
        hint, noise, steps, done = 0, 0.0, 0, False
        while not done:
            tr = info["truth"]
            u, du, hint = expert.labels(tr["x"], tr["y"], tr["heading"], hint, offsets)
            if args.side_labels == "geometric":
                u = {name: geometric_side_label(u["centre"], off, args.recovery_distance, max_steering)
                     for name, off in offsets.items()}
                du = {name: du["centre"] for name in offsets}
            for c, name in enumerate(CAMERAS):
                rows["images"].append(obs["cameras"][name])
                rows["steering"].append(u[name])
                rows["dsteer_dyaw"].append(du[name])
                rows["camera"].append(c)
            for key, value in (("frame", frame), ("lap", lap), ("seed", seed), ("cte", tr["cte"]),
                               ("heading_error", tr["heading_error"]), ("progress", tr["progress"])):
                rows[key] += [value] * len(CAMERAS)
            # Ornstein-Uhlenbeck perturbation of the executed steering (the label stays the clean command).
            noise += -noise * dt / args.perturb_tau + args.perturb_std * math.sqrt(2 * dt / args.perturb_tau) \
                * rng.standard_normal()
            action = np.array([np.clip(u["centre"] + noise, -1.0, 1.0)], dtype=np.float32)
            obs, _, terminated, truncated, info = env.step(action)
            frame, steps = frame + 1, steps + 1
            done = terminated or truncated or (args.demo_max_steps is not None and steps >= args.demo_max_steps)
        m = info.get("episode_metrics", {})
        log(f"[bc] demo lap {lap + 1}/{args.demo_laps} (seed {seed}): {steps} steps, "
            f"lap completed {bool(m.get('lap_completed', 0))}, {demo_cte_text(m)} with perturbations "
            f"({time.time() - t0:.0f} s)")
    env.close()
    demos = {k: np.asarray(v) for k, v in rows.items()}
    demos["images"] = demos["images"].astype(np.uint8)
    for k in ("steering", "dsteer_dyaw", "cte", "heading_error", "progress"):
        demos[k] = demos[k].astype(np.float32)
    for k, dtype in (("camera", np.int8), ("frame", np.int32), ("lap", np.int16), ("seed", np.int64)):
        demos[k] = demos[k].astype(dtype)
    spec = cam["centre"]
    demos["meta"] = {"version": DEMO_VERSION, "track": u_env.config["track"], "policy_frequency": 1 / dt,
                     "cameras": list(CAMERAS), "camera_offsets": offsets, "focal_px": spec.focal,
                     "image_shape": [spec.height, spec.width, 3], "expert": "pure_pursuit",
                     "lookahead": args.lookahead, "perturb_std": args.perturb_std, "perturb_tau": args.perturb_tau,
                     "side_labels": args.side_labels, "max_steering": max_steering, "laps": args.demo_laps}
    return demos


def save_demos(demos: dict, path: str | Path) -> Path:
    """``np.savez_compressed``: uint8 images (N, H, W, 3), float32 labels, int indices, and ``meta`` as JSON text
    (no pickles, so loading needs ``allow_pickle=False`` only)."""
    arrays = {k: v for k, v in demos.items() if k != "meta"}
    with atomic_path(path, "agent.demos") as tmp, open(tmp, "wb") as f:  # a file object: savez adds no suffix
        np.savez_compressed(f, meta=np.array(json.dumps(demos["meta"])), **arrays)
    return Path(path)


def load_demos(path: str | Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        demos = {k: z[k] for k in z.files}
    demos["meta"] = json.loads(str(demos["meta"]))
    if demos["meta"].get("version") != DEMO_VERSION:
        raise ValueError(f"{path}: demos version {demos['meta'].get('version')}, expected {DEMO_VERSION}")
    return demos


# ================================================================================================ 4. balancing, split
def balance(steering: np.ndarray, bins: int = 25, cap: int | None = None, cap_factor: float = 2.0,
            rng: np.random.Generator | None = None) -> tuple[np.ndarray, int]:
    """Indices (sorted) of a subset in which no steering bin (``bins`` equal bins over [−1, 1]) holds more than
    ``cap`` samples; ``cap`` defaults to ``cap_factor`` × the median non-empty bin count. Returns (indices, cap)."""
    rng = rng or np.random.default_rng(0)
    b = np.clip(((np.asarray(steering) + 1.0) / 2.0 * bins).astype(int), 0, bins - 1)
    counts = np.bincount(b, minlength=bins)
    if cap is None:
        cap = max(1, int(cap_factor * np.median(counts[counts > 0])))
    keep = []
    for i in range(bins):
        idx = np.flatnonzero(b == i)
        keep.append(rng.choice(idx, size=cap, replace=False) if len(idx) > cap else idx)
    return np.sort(np.concatenate(keep)), int(cap)


def split_by_chunks(frame: np.ndarray, lap: np.ndarray, chunk_steps: int, val_fraction: float,
                    rng: np.random.Generator) -> np.ndarray:
    """Boolean validation mask: contiguous chunks of ``chunk_steps`` frames (per lap) go wholly to one side."""
    first = {int(l_): int(frame[lap == l_].min()) for l_ in np.unique(lap)}
    chunk = np.array([f"{l_}:{(f - first[int(l_)]) // chunk_steps}" for f, l_ in zip(frame, lap)])
    names = np.unique(chunk)
    n_val = max(1, int(round(val_fraction * len(names)))) if len(names) > 1 else 0
    val_names = set(rng.choice(names, size=n_val, replace=False).tolist()) if n_val else set()
    mask = np.array([c in val_names for c in chunk])
    if not mask.any():  # too little data for a chunked split (tests): hold out every fifth frame
        mask = frame % 5 == 4
    return mask


# ================================================================================================ 5. augmentation
@dataclass(frozen=True)
class WeatherMaps:
    """Per-pixel ground distance (m; capped at 1 km, the sky included) and headlight beam factor of the demo
    camera, both (66, 200) float32 after the same crop/resize as the images: what :class:`av_gym.sensors.camera.
    Weather` needs to turn a clean frame into a foggy or night one (vertical things are treated as the ground
    behind them: nearer in truth, so augmented fog on them is a little thicker than the camera's)."""

    depth: torch.Tensor
    beam: torch.Tensor

    @classmethod
    def for_camera(cls, camera_cfg: dict, crop_top: int) -> WeatherMaps:
        from av_gym.sensors.camera import CameraSpec
        from av_gym.sensors.camera_render import _ground_rays

        keys = ("height", "width", "hfov_deg", "mount_height", "pitch_deg", "forward_offset", "max_range",
                "supersample")
        spec = CameraSpec(**{k: camera_cfg[k] for k in keys if k in camera_cfg})
        depth, beam = (np.array(a, np.float32) for a in _ground_rays(spec))
        out = []
        for a in (np.minimum(depth, 1000.0), beam):
            a = cv2.resize(a, (spec.width, spec.height), interpolation=cv2.INTER_AREA)[crop_top:]
            out.append(torch.from_numpy(cv2.resize(a, (INPUT_WIDTH, INPUT_HEIGHT), interpolation=cv2.INTER_LINEAR)))
        return cls(*out)


def augment(rgb: torch.Tensor, y: torch.Tensor, dy_dyaw: torch.Tensor, args: PilotNetParams, focal_px: float,
            gen: torch.Generator, weather: WeatherMaps | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Random conditions (fog, night; needs ``weather``), flip, shift (as yaw, label corrected), vertical shift,
    roll, exposure, blur and pixel noise on a float RGB batch (B, 3, H, W) in [0, 255]; returns the augmented batch
    and labels (see the module docstring). Fog and night follow the camera model's equations
    (``av_gym/sensors/camera.py: _apply_weather``) with parameters drawn per image around its defaults."""
    b, _, h, w = rgb.shape

    def uniform(lo: float, hi: float, n: int = b) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(n, generator=gen, device=gen.device)

    night = torch.zeros(b, dtype=torch.bool, device=rgb.device)
    if weather is not None and (args.fog_p > 0 or args.night_p > 0):
        fog = torch.rand(b, generator=gen, device=gen.device) < args.fog_p
        night = torch.rand(b, generator=gen, device=gen.device) < args.night_p
        vis = torch.exp(uniform(math.log(args.fog_min_m), math.log(args.fog_max_m)))[:, None, None, None]
        t = torch.exp(-3.912 * weather.depth / vis)
        rgb = torch.where(fog[:, None, None, None], rgb * t + 200.0 * (1 - t), rgb)  # airlight 200 (camera's)
        ambient = uniform(0.3, 0.5)[:, None, None, None]
        gamma = uniform(1.5, 2.2)[:, None, None, None]
        light = ambient + (1 - ambient) * weather.beam / (1 + (weather.depth / 20.0) ** 2)
        dark = 255.0 * (rgb * light / 255.0).clamp(0.0, 1.0) ** gamma
        rgb = torch.where(night[:, None, None, None], dark, rgb)

    flip = torch.rand(b, generator=gen, device=gen.device) < args.flip_p
    rgb = torch.where(flip[:, None, None, None], rgb.flip(-1), rgb)
    y = torch.where(flip, -y, y)

    tx = uniform(-args.shift_px, args.shift_px)  # px, + = content moves right = camera yawed left
    ty = uniform(-args.vshift_px, args.vshift_px)
    roll = torch.deg2rad(uniform(-args.rotate_deg, args.rotate_deg))
    y = (y + dy_dyaw * -torch.atan(tx / focal_px)).clamp(-1.0, 1.0)
    if args.shift_px or args.vshift_px or args.rotate_deg:
        # affine_grid maps output to input coordinates in [-1, 1]²: input = R·output − 2·t/size (aspect-corrected).
        cos, sin = torch.cos(roll), torch.sin(roll)
        theta = torch.stack([torch.stack([cos, -sin * h / w, -2 * tx / w], 1),
                             torch.stack([sin * w / h, cos, -2 * ty / h], 1)], 1)
        grid = F.affine_grid(theta, list(rgb.shape), align_corners=False)
        rgb = F.grid_sample(rgb, grid, mode="bilinear", padding_mode="border", align_corners=False)

    contrast = uniform(1 - args.contrast, 1 + args.contrast)[:, None, None, None]
    offset = uniform(-args.brightness, args.brightness)[:, None, None, None]
    gain = uniform(1 - args.gain, 1 + args.gain)[:, None, None, None]
    rgb = ((rgb - 128.0) * contrast + 128.0 + offset) * gain
    if args.blur_p > 0 and args.blur_max_px > 0:
        # one σ per batch (a separable Gaussian kernel), applied to a random share of the images
        sigma_b = float(uniform(0.0, args.blur_max_px, 1))
        if sigma_b > 0.05:
            r = max(1, int(math.ceil(3 * sigma_b)))
            k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float32, device=rgb.device) / sigma_b) ** 2)
            k = (k / k.sum()).to(rgb.dtype)
            blurred = F.conv2d(F.pad(rgb, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).repeat(3, 1, 1, 1),
                               groups=3)
            blurred = F.conv2d(F.pad(blurred, (0, 0, r, r), mode="replicate"),
                               k.view(1, 1, -1, 1).repeat(3, 1, 1, 1), groups=3)
            pick = torch.rand(b, generator=gen, device=gen.device) < args.blur_p
            rgb = torch.where(pick[:, None, None, None], blurred, rgb)
    sigma = uniform(0.0, args.pixel_noise)
    if night.any():
        sigma = torch.where(night, uniform(0.0, args.night_pixel_noise), sigma)
    rgb = rgb + sigma[:, None, None, None] * torch.randn(rgb.shape, generator=gen, device=gen.device)
    return rgb.clamp(0.0, 255.0), y


# ================================================================================================ 6. training
def _save_atomic(obj: Any, path: Path) -> Path:
    """``torch.save`` through :func:`av_gym.atomic.atomic_path` (a crash never leaves a torn file)."""
    with atomic_path(path, "paths.checkpoints") as tmp:
        torch.save(obj, tmp)
    return path


def _as_batch(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(images).permute(0, 3, 1, 2).float()


@torch.no_grad()
def _evaluate(model: PilotNet, x: np.ndarray, y: np.ndarray, batch: int = 500) -> float:
    model.eval()
    device = _device_of(model)
    se = 0.0
    for i in range(0, len(x), batch):
        pred = model(to_network_input(_as_batch(x[i:i + batch]).to(device)))
        se += float(((pred - torch.from_numpy(y[i:i + batch]).to(device)) ** 2).sum())
    return se / max(1, len(x))


def _device_of(model: torch.nn.Module) -> torch.device:
    return next(model.parameters()).device


def _cpu_state(model: torch.nn.Module) -> dict:
    """The state dict to save: CPU tensors whatever the training device (eval loads with map_location=cpu, but a
    checkpoint should not name a GPU). On the CPU it is the state dict itself, so the file is as before."""
    state = model.state_dict()
    if _device_of(model).type == "cpu":
        return state
    return type(state)((k, v.detach().cpu()) for k, v in state.items())


def drive_laps(model: PilotNet, crop_top: int, env_cfg: dict, sensors_cfg: dict, seeds) -> list[dict]:
    """Closed-loop check: PilotNet drives one lap per seed from the (noisy) centre camera; episode metric rows."""
    from agents.pilotnet import PilotNetPolicy
    from av_gym.make import make_env

    env = make_env(env_cfg, sensors_cfg)
    policy, rows = PilotNetPolicy(model, crop_top), []
    for seed in seeds:
        obs, _ = env.reset(seed=int(seed))
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy.act(obs))
            done = terminated or truncated
        rows.append(info["episode_metrics"])
    env.close()
    return rows


@dataclass
class _Samples:
    """The demonstrations split and preprocessed once (cropped, resized): training side balanced."""

    x_train: np.ndarray
    y_train: np.ndarray
    s_train: np.ndarray  # d steering / d yaw of each training sample (the augmentation's label shift)
    x_val: np.ndarray
    y_val: np.ndarray
    focal: float
    weather: Any


def train(args: PilotNetParams, env_cfg: dict, sensors_cfg: dict, run_dir: str | Path, ckpt_dir: str | Path,
          log: Callable[[str], None] = print) -> Path:
    """The whole pipeline; returns the path of the best checkpoint (``ckpt_dir/model.pt``)."""
    from torch.utils.tensorboard import SummaryWriter

    run_dir, ckpt_dir = Path(run_dir), Path(ckpt_dir)
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    rng = np.random.default_rng(_seed(args))
    torch.manual_seed(_seed(args))
    gen = torch.Generator().manual_seed(_seed(args))
    threads = torch.get_num_threads()
    torch.set_num_threads(args.torch_threads)
    writer = SummaryWriter(str(run_dir / "tb"))
    best, best_epoch, best_path = float("inf"), -1, ckpt_dir / "model.pt"
    stage = "collecting demonstrations"
    try:
        demos = _demonstrations(args, env_cfg, sensors_cfg, run_dir, log)
        t_demos = time.time() - t_start
        data = _samples(demos, args, sensors_cfg, rng, writer, log)
        del demos
        # model, optimiser: initialised on the CPU (the same weights on every device), then moved
        device = resolve_device(args.device)
        with torch.device("cpu"):
            model = PilotNet(dropout=args.dropout)
        model.to(device)
        opt = torch.optim.Adam(model.parameters(), lr=args.learning_rate)
        log(f"[bc] PilotNet: {count_parameters(model):,} parameters on {device}; Adam lr {args.learning_rate}, "
            f"batch {args.batch_size}, up to {args.epochs} epochs, patience {args.patience}")
        bad = 0
        for epoch in range(args.epochs):
            stage = f"training epoch {epoch + 1}/{args.epochs}"
            t0 = time.time()
            train_loss = _epoch(model, opt, data, args, gen, device, writer, epoch)
            val_loss = _evaluate(model, data.x_val, data.y_val) if len(data.x_val) else train_loss
            writer.add_scalar("loss/train", train_loss, epoch)
            writer.add_scalar("loss/val", val_loss, epoch)
            writer.add_scalar("time/epoch_s", time.time() - t0, epoch)
            closed = _closed_loop(model, args, env_cfg, sensors_cfg, writer, epoch) if args.closed_loop_laps else ""
            improved = val_loss < best
            if improved:
                best, best_epoch, bad = val_loss, epoch, 0
                _save_best(model, args, epoch, val_loss, train_loss, best_path)
            else:
                bad += 1
            log(f"[bc] epoch {epoch + 1:2d}/{args.epochs}: train MSE {train_loss:.4f}  val MSE {val_loss:.4f}"
                f"{closed}{'  (best, saved)' if improved else ''}  {time.time() - t0:.0f} s")
            if bad >= args.patience:
                log(f"[bc] early stop: no better validation loss for {args.patience} epochs")
                break
        if len(data.x_val):
            writer.add_images("samples/validation_rgb",
                              _as_batch(data.x_val[:: max(1, len(data.x_val) // 16)][:16]) / 255.0, 0)
        writer.add_scalar("loss/best_val", best, best_epoch)
        log(f"[bc] best epoch {best_epoch + 1} (val MSE {best:.4f}); demos {t_demos:.0f} s, total "
            f"{time.time() - t_start:.0f} s")
        return best_path
    except KeyboardInterrupt:  # Ctrl-C / SIGTERM: say what is kept (rather than exit 130 without a word)
        kept = (f"{best_path} holds epoch {best_epoch + 1}, the best so far (val MSE {best:.4f})" if best_epoch >= 0
                else "no model was saved yet")
        print(f"[bc] interrupted while {stage}: {kept}", file=sys.stderr)
        raise
    finally:
        writer.close()
        torch.set_num_threads(threads)


def _demonstrations(args: PilotNetParams, env_cfg: dict, sensors_cfg: dict, run_dir: Path, log) -> dict:
    """Collected (and stored under the run folder), or reused from ``agent.demos``."""
    if args.demos:
        demos = load_demos(args.demos)
        log(f"[bc] reusing {len(demos['steering'])} samples from {args.demos}")
        return demos
    demos = collect_demos(env_cfg, sensors_cfg, args, log)
    path = save_demos(demos, run_dir / "demos.npz")
    log(f"[bc] {len(demos['steering'])} samples ({len(demos['steering']) // 3} frames × 3 cameras) -> {path} "
        f"({path.stat().st_size / 1e6:.1f} MB); reuse with agent.demos={path}")
    return demos


def _samples(demos: dict, args: PilotNetParams, sensors_cfg: dict, rng, writer, log) -> _Samples:
    """Split by chunks of driving, balance the training side, preprocess once (crop/resize)."""
    meta = demos["meta"]
    writer.add_histogram("data/steering_all", demos["steering"], 0)
    chunk_steps = max(1, int(round(args.val_chunk_s * meta["policy_frequency"])))
    val = split_by_chunks(demos["frame"], demos["lap"], chunk_steps, args.val_fraction, rng)
    train_idx = np.flatnonzero(~val)
    kept, cap = balance(demos["steering"][train_idx], args.bins, args.bin_cap, args.cap_factor, rng)
    train_idx = train_idx[kept]
    val_idx = np.flatnonzero(val)
    writer.add_histogram("data/steering_balanced", demos["steering"][train_idx], 0)
    log(f"[bc] split: {len(train_idx)} training samples after balancing (cap {cap} per bin of {args.bins}), "
        f"{len(val_idx)} validation samples")
    weather = WeatherMaps.for_camera(sensors_cfg["cameras"], args.crop_top) \
        if (args.fog_p > 0 or args.night_p > 0) else None
    return _Samples(crop_resize(demos["images"][train_idx], args.crop_top),
                    demos["steering"][train_idx].astype(np.float32),
                    demos["dsteer_dyaw"][train_idx].astype(np.float32),
                    crop_resize(demos["images"][val_idx], args.crop_top),
                    demos["steering"][val_idx].astype(np.float32), float(meta["focal_px"]), weather)


def _epoch(model: PilotNet, opt, data: _Samples, args: PilotNetParams, gen: torch.Generator, device, writer,
           epoch: int) -> float:
    """One pass over the training samples in a random order, augmented; returns the mean training MSE."""
    model.train()
    n = len(data.x_train)
    perm = torch.randperm(n, generator=gen, device="cpu").numpy()
    total = 0.0
    for i in range(0, n, args.batch_size):
        idx = np.sort(perm[i:i + args.batch_size])
        rgb, y = augment(_as_batch(data.x_train[idx]), torch.from_numpy(data.y_train[idx]),
                         torch.from_numpy(data.s_train[idx]), args, data.focal, gen, data.weather)
        if epoch == 0 and i == 0:
            writer.add_images("samples/augmented_rgb", rgb[:16] / 255.0, 0)
            writer.add_text("samples/augmented_labels", " ".join(f"{v:+.2f}" for v in y[:16].tolist()), 0)
        # augmented on the CPU (its generator's stream), learned on the device
        loss = F.mse_loss(model(to_network_input(rgb.to(device))), y.to(device))
        opt.zero_grad()
        loss.backward()
        opt.step()
        total += loss.item() * len(idx)
    return total / n


def _closed_loop(model: PilotNet, args: PilotNetParams, env_cfg: dict, sensors_cfg: dict, writer, epoch: int) -> str:
    """``agent.closed_loop_laps`` laps driven by the model after the demonstration seeds; TensorBoard scalars and
    the epoch line's summary."""
    seeds = range(args.demo_seed + args.demo_laps, args.demo_seed + args.demo_laps + args.closed_loop_laps)
    rows = drive_laps(model, args.crop_top, env_cfg, sensors_cfg, seeds)
    for key in ("lap_completed", "cte_mean_abs_units", "cte_max_abs_units", "steering_sign_changes_per_100m"):
        writer.add_scalar(f"closed_loop/{key}", float(np.mean([r[key] for r in rows])), epoch)
    return (f"  lap {np.mean([r['lap_completed'] for r in rows]):.0%} "
            f"|CTE| {np.mean([r['cte_mean_abs_units'] for r in rows]):.2f} units")


def _save_best(model: PilotNet, args: PilotNetParams, epoch: int, val_loss: float, train_loss: float,
               path: Path) -> None:
    _save_atomic({"format": FORMAT, "state_dict": _cpu_state(model),
                  "preprocess": {"crop_top": int(args.crop_top), "colour": "yuv_bt601",
                                 "normalise": "x/127.5-1", "input": [3, 66, 200]},
                  "epoch": epoch, "val_loss": float(val_loss), "train_loss": float(train_loss),
                  "args": {k: v for k, v in args.as_dict().items()
                           if v is not None and k not in AgentParams.field_names()}}, path)


def _seed(args: PilotNetParams) -> int:
    """``seed`` null means the run's seed (:func:`train_pilotnet` fills it in); 0 when called from Python."""
    return 0 if args.seed is None else int(args.seed)


# ================================================================================================ 7. the trainer
def _sensors(cfg: DictConfig) -> dict:
    """The sensors preset PilotNet uses: the command line's if it has cameras, else the agent's own."""
    from eval.agents import compose_group  # train -> eval: python -m eval's composition of a group

    sensors = OmegaConf.to_container(cfg.sensors, resolve=True)
    if "cameras" in sensors:
        return sensors
    return compose_group("sensors", str(cfg.agent.get("sensors", "cameras")))


def validate(cfg: DictConfig) -> list[str]:
    """What PilotNet's training needs beyond its Params (checked by the config checker), as one-line messages."""
    problems = device_problems(str(cfg.agent.device))
    if cfg.env.name != "lane_keeping":
        problems.append(f"agent pilotnet drives env=lane_keeping, not env={cfg.env.name}")
    try:
        if "cameras" not in _sensors(cfg):
            problems.append(f"agent.sensors={cfg.agent.get('sensors')!r} gives no cameras; PilotNet needs a "
                            f"preset with cameras (e.g. cameras)")
    except ValueError as exc:
        problems.append(f"agent.sensors: {exc}")
    from av_gym.seeds import seeds

    agent = cfg.agent
    try:  # expert laps and the closed-loop laps it is checked on: train seeds only (av_gym/seeds.py)
        seeds("train", int(agent.demo_laps) + int(agent.get("closed_loop_laps", 0)), int(agent.demo_seed),
              field="agent.demo_seed")
    except ValueError as exc:
        problems.append(str(exc))
    return problems


def train_pilotnet(cfg: DictConfig, ckpt_dir: Path, run_dir: Path, command: TrainCommand | None = None) -> Path:
    """Collect demonstrations, train, write ``ckpt_dir/model.pt`` (best validation loss) and ``config.yaml``
    (with the camera sensors preset); returns the model path. ``command``: the run's settings (default: read from
    ``cfg``)."""
    from train.checkpoint import write_text_atomic

    command = command or TrainCommand.of(cfg)
    sensors = _sensors(cfg)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    resolved["sensors"] = sensors
    write_text_atomic(Path(ckpt_dir) / "config.yaml", OmegaConf.to_yaml(OmegaConf.create(resolved)))
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    params = PilotNetParams.from_mapping(OmegaConf.to_container(cfg.agent, resolve=True), where="agent")
    if params.seed is None:  # the run's seed
        params = replace(params, seed=command.seed)
    return train(params, env_cfg, sensors, run_dir, ckpt_dir)


__all__ = ["PurePursuitExpert", "geometric_side_label", "collect_demos", "save_demos", "load_demos", "balance",
           "split_by_chunks", "augment", "train", "train_pilotnet", "validate"]
