"""Three windshield cameras (left, centre, right): pinhole perspective renders of the road, its markings, the
roadside world and the other vehicles, for PilotNet behaviour cloning (digest 001 §2, §8.5a).

Geometry
--------
Each camera sits on the windshield at ``forward_offset`` ahead of the vehicle's reference point (its centre in
highway-env), ``lateral_offset`` across it (+ = driver's right, highway-env's lateral sign) and ``mount_height``
above the ground, looks along the vehicle heading (plus an optional ``yaw_deg``) and is pitched down by
``pitch_deg``. The rig puts the side cameras at ``lateral_offset = ∓d`` with ``d =`` :data:`WINDSHIELD_HALF_WIDTH`
= 0.6 m (our choice: the half-width of a car's windshield; digest 001 §8.5 suggests 0.8–1.0 m, which would sit
outside the glass of highway-env's 2 m-wide car).

World point ``(x, y, z)`` (highway-env frame: x right, y down on screen, z up, metres) → vehicle-aligned
``a`` (forward), ``b`` (right), ``u = z − mount_height`` (up) → camera frame (OpenCV convention: X right, Y down,
Z along the optical axis) ``X = b``, ``Y = −(a·sinθ + u·cosθ)``, ``Z = a·cosθ − u·sinθ`` (θ = pitch) → pixels
``col = cx + f·X/Z``, ``row = cy + f·Y/Z`` with ``f = (W/2)/tan(hfov/2)`` (square pixels). Polygons are clipped
against the near plane ``Z = NEAR_PLANE`` (Sutherland–Hodgman) before the division, so geometry beside or behind
the camera never folds over the image.

Drawing (painter's algorithm): sky gradient and grass (precomputed per camera) → asphalt of every lane →
lane markings (edge lines for ``CONTINUOUS`` sides, 3 m dashes every 9 m for ``STRIPED`` sides, nothing for
``NONE``) → vertical things far to near: roadside walls (guard rails, building fronts) as ground-to-height quads,
cylinders (poles, sign posts, trees) as camera-facing rectangles ``2r`` wide, other vehicles as
:data:`VEHICLE_HEIGHT`-tall boxes with back faces culled. Scenery shapes are exactly :mod:`av_gym.sensors.world`'s,
so the camera and the LiDAR see the same world. Rendering is done at ``supersample``× the output size and
averaged down with ``cv2.resize(INTER_AREA)`` (anti-aliasing).

Conditions and noise
--------------------
Deterministic conditions (:class:`Weather`, applied by :func:`render_view`): fog as an airlight blend
``I' = I·t + A·(1 − t)`` (digest 000 §5.7) with per-pixel transmission ``t = exp(−3.912·d/V)`` (Koschmieder's law,
visibility ``V``, distance ``d`` from a depth buffer; our choice), and night (darken by an ambient factor plus
headlight pools, then a gamma; digest 000 §5.7 ranges). Random sensor noise (:class:`CameraNoise`, drawn from the
wrapper's ``self.rng``): per-episode brightness/contrast and per-camera gain, optional Gaussian blur, per-frame
Gaussian pixel noise.

The code, by seam: the specs, the look and the scene built once per map (:mod:`av_gym.sensors.camera_scene`),
rendering images from it (:mod:`av_gym.sensors.camera_render`, with the compiled painter
:mod:`av_gym.sensors.raster`), and here the sensor wrapper :class:`Cameras` with its noise; this module re-exports
the public names.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from av_gym.params import RATE_MAX_HZ, Params, param
from av_gym.sensors.base import SensorWrapper, sim_time
from av_gym.sensors.camera_render import render_view, render_views
from av_gym.sensors.camera_scene import (ASPHALT, CAMERA_NAMES, MARKING, NEAR_PLANE, VEHICLE_HEIGHT,
                                         WINDSHIELD_HALF_WIDTH, CameraSpec, GroundTexture, StaticScene, Weather, build_scene, camera_rig,
                                         ground_texture, scene_of)


NOISE_BANK_SIZE = 1 << 21  # standard normals drawn once per process for the pixel noise (Cameras._pixel_noise)
NOISE_BANK_SEED = 18  # the bank's generator seed: the same bank in every process


@dataclass(frozen=True)
class CameraNoise(Params):
    """Random sensor noise, all drawn from the wrapper's generator (a section of :class:`CamerasParams`). Applied
    in this order: exposure (brightness, contrast, camera_gain), blur, pixel noise, clip to [0, 255], round."""

    pixel_std: float = param(3.0, "8-bit", ge=0, doc="per-frame Gaussian pixel noise by day, independent per pixel "
                                                     "and channel (digest 000: 2-8)")
    night_pixel_std: float = param(12.0, "8-bit", ge=0, doc="pixel noise at night (digest 000: 8-20)")
    brightness: float = param(15.0, "8-bit", ge=0, doc="per-episode offset, uniform in ±this (our choice)")
    contrast: float = param(0.15, ge=0, lt=1, doc="per-episode gain about mid-grey 128, uniform in 1 ± this (our "
                                                  "choice)")
    camera_gain: float = param(0.10, ge=0, lt=1, doc="per-episode, per-camera gain, uniform in 1 ± this (digest "
                                                     "000: inter-camera exposure mismatch ±10 %)")
    blur_sigma: float = param(0.0, "px", ge=0, doc="Gaussian blur σ in output pixels; 0 = off (our choice)")


@lru_cache(maxsize=1)
def _noise_bank() -> np.ndarray:
    """:data:`NOISE_BANK_SIZE` float32 standard normals from a generator seeded with :data:`NOISE_BANK_SEED`."""
    return np.random.default_rng(NOISE_BANK_SEED).standard_normal(NOISE_BANK_SIZE, dtype=np.float32)


# Pixels rendered per camera and frame (height x width x supersample²): the renderer holds a few float arrays of this
# size per camera; 2**23 (e.g. 1024 x 2048 at supersample 2) is ~0.2 GB per camera, where 10000 x 10000 asked for
# 8.9 GiB. PilotNet's input is 66 x 200.
RENDER_PIXELS_MAX = 2**23


# ================================================================================================ the wrapper
@dataclass(frozen=True)
class CamerasParams(Params):
    """Three windshield cameras, left/centre/right (digest 001 §2, §8.5; 000 §5.7); see :class:`CameraSpec`."""

    height: int = param(66, "px", ge=2, le=2160, doc="image height (PilotNet input, paper 001 Table 1); <= 4K")
    width: int = param(200, "px", ge=2, le=3840, doc="image width (PilotNet input); <= 4K")
    hfov_deg: float = param(70.0, "deg", ge=1, le=170, doc="horizontal field of view (our choice: a 4 m lane "
                                                           "fills about a third of the bottom row)")
    mount_height: float = param(1.4, "m", gt=0, doc="lens height above the ground")
    pitch_deg: float = param(8.0, "deg", gt=-90, lt=90, doc="downward pitch (digest 001 §8.5: 5-10°)")
    lateral_offset: float = param(WINDSHIELD_HALF_WIDTH, "m", doc="side cameras at ±this across the windshield "
                                                                  "(half a windshield; 001 suggests 0.8-1.0)")
    forward_offset: float = param(0.5, "m", doc="ahead of the vehicle centre (the windshield of a 5 m car)")
    max_range: float = param(80.0, "m", gt=0, doc="nothing is drawn beyond")
    supersample: int = param(2, ge=1, le=8, doc="render at this factor, shrink with area averaging "
                                                "(anti-aliasing)")
    rate_hz: float | None = param(None, "Hz", gt=0, le=RATE_MAX_HZ, doc="capture rate; null = every policy step; lower values hold "
                                                        "the last frame")
    noise: CameraNoise | None = param(CameraNoise(), doc="sensor noise; null = clean renders (bit-identical to "
                                                         "render_views)")
    fog_visibility: float | None = param(None, "m", gt=0, doc="fog visibility (null = clear); see Weather")
    night: bool = param(False, doc="night-time rendering; see Weather")
    weather: Weather | None = param(None, doc="a full Weather section; overrides fog_visibility and night")
    views: tuple[Literal["left", "centre", "right"], ...] = param(
        CAMERA_NAMES, doc="the cameras rendered (camera_centre: [centre]). The per-episode exposure is drawn for "
                          "all three whatever the subset, so a subset's camera has the same exposure as in the rig")

    def relations(self) -> list[str]:
        if not self.views:
            return [f"@views must be a non-empty subset of {list(CAMERA_NAMES)}, got []"]
        rendered = self.height * self.width * self.supersample**2
        if rendered > RENDER_PIXELS_MAX:
            return [f"@height x @width x @supersample² must be at most {RENDER_PIXELS_MAX} rendered pixels per "
                    f"camera, got {self.height} x {self.width} x {self.supersample}² = {rendered}"]
        return []


class Cameras(SensorWrapper):
    """Adds ``obs["cameras"] = {"left", "centre", "right"}``: three (H, W, 3) uint8 RGB windshield images (or the
    subset named by ``views``); parameters: :class:`CamerasParams`. From Python, ``noise`` may also be ``True``
    (the defaults) or ``False`` (clean renders), and ``noise``/``weather`` instances.

    Example: 66×200 RGB frames from three cameras, here in fog of 80 m visibility:

        >>> import gymnasium as gym
        >>> import av_gym
        >>> from av_gym.sensors.camera import Cameras
        >>> env = Cameras(gym.make("av_gym/LaneKeepingLap-v0"), fog_visibility=80.0)
        >>> obs, info = env.reset(seed=0)
        >>> sorted(obs["cameras"]), obs["cameras"]["centre"].shape, obs["cameras"]["centre"].dtype
        (['centre', 'left', 'right'], (66, 200, 3), dtype('uint8'))

    Building one sets OpenCV to one thread for the process (``cv2.setNumThreads(1)``): its thread pool splits each
    66×200 remap and colour conversion across cores, which bought 0.05 ms of a 3.2 ms left-turn `full` step for
    0.8 ms more CPU on 2 idle cores (``python benchmarks/sensor_cost.py``), and an RL run steps one
    environment per core anyway."""

    key = "cameras"
    Params = CamerasParams

    def __init__(self, env: gym.Env, params: CamerasParams | None = None, **overrides) -> None:
        if isinstance(overrides.get("noise"), bool):
            overrides["noise"] = CameraNoise().as_dict() if overrides["noise"] else None
        for key in ("noise", "weather"):  # sections given as instances: checked as their fields
            if isinstance(overrides.get(key), Params):
                overrides[key] = overrides[key].as_dict()
        p = self.params = CamerasParams.build(params, **overrides)
        base = CameraSpec(height=int(p.height), width=int(p.width), hfov_deg=float(p.hfov_deg),
                          mount_height=float(p.mount_height), pitch_deg=float(p.pitch_deg),
                          forward_offset=float(p.forward_offset), max_range=float(p.max_range),
                          supersample=int(p.supersample))
        rig = camera_rig(base, float(p.lateral_offset))
        self.specs = {name: rig[name] for name in CAMERA_NAMES if name in p.views}
        self.weather = p.weather or Weather(fog_visibility=p.fog_visibility, night=bool(p.night))
        self.noise: CameraNoise | None = p.noise
        self.rate_hz = p.rate_hz
        cv2.setNumThreads(1)
        super().__init__(env)
        self._exposure = {name: (1.0, 0.0) for name in CAMERA_NAMES}  # name → (gain, offset)
        self._held: dict[str, np.ndarray] | None = None
        self._next_capture = 0.0

    def sensor_space(self) -> spaces.Dict:
        return spaces.Dict({name: spaces.Box(0, 255, (spec.height, spec.width, 3), np.uint8)
                            for name, spec in self.specs.items()})

    def on_reset(self) -> None:
        self._held, self._next_capture = None, 0.0
        n = self.noise
        if n is None:
            return
        # Per-episode exposure: I' = ((I − 128)·contrast + 128 + brightness)·gain_k = I·g + o per camera.
        brightness = self.rng.uniform(-n.brightness, n.brightness)
        contrast = self.rng.uniform(1 - n.contrast, 1 + n.contrast)
        gains = self.rng.uniform(1 - n.camera_gain, 1 + n.camera_gain, size=len(CAMERA_NAMES))
        self._exposure = {name: (float(contrast * g), float((128.0 * (1 - contrast) + brightness) * g))
                          for name, g in zip(CAMERA_NAMES, gains)}

    def _noisy(self, name: str, clean: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
        """Exposure, blur and pixel noise on one clean frame; ``noise`` (H, W, 3) float32 standard normals (see
        :meth:`_pixel_noise`), None without pixel noise."""
        n = self.noise
        gain, offset = self._exposure[name]
        sigma = n.night_pixel_std if self.weather.night else n.pixel_std
        im = clean.astype(np.float32)
        if n.blur_sigma > 0:
            im = cv2.GaussianBlur(im * np.float32(gain) + np.float32(offset), (0, 0), n.blur_sigma)
            gain, offset = 1.0, 0.0
        # exposure, pixel noise, rounding and clipping to [0, 255] in one OpenCV pass (saturate_cast rounds to
        # nearest)
        return cv2.addWeighted(im, float(gain), im if noise is None else noise, float(sigma) if noise is not None
                               else 0.0, float(offset), dtype=cv2.CV_8U)

    def _pixel_noise(self) -> dict[str, np.ndarray] | None:
        """This frame's standard normals, name → (H, W, 3) float32, or None when the pixel noise is off.

        Drawing 40k Gaussians per 66x200 camera cost as much as rendering it (~0.15-0.4 ms), so they come from a
        bank of :data:`NOISE_BANK_SIZE` standard normals drawn once per process from a generator seeded with
        :data:`NOISE_BANK_SEED`: each frame the wrapper's generator draws one uniform offset and the rig's cameras
        take consecutive windows of the bank from there. Within a frame every value is a distinct draw, so each
        pixel, channel and camera is independent N(0, 1) as before. Across frames the offsets are independent,
        so a pixel's noise in two frames is the same value only if the offsets coincide (probability 1/2^21) and
        its correlation between frames is ~0 (tested); but two frames whose offsets are closer than the rig's
        pixel count (about 2·119k/2^21 ≈ 11 % of frame pairs for the 3 x 66x200 rig) share part of their noise
        pattern shifted by the offset difference, and an episode's noise patterns are windows of one fixed 8 MB
        bank. Images too large for the bank (over half of it) draw their normals directly."""
        n = self.noise
        if (n.night_pixel_std if self.weather.night else n.pixel_std) <= 0:
            return None
        sizes = [spec.height * spec.width * 3 for spec in self.specs.values()]
        total = sum(sizes)
        if total > NOISE_BANK_SIZE // 2:
            return {name: self.rng.standard_normal((spec.height, spec.width, 3), dtype=np.float32)
                    for name, spec in self.specs.items()}
        start = int(self.rng.integers(0, NOISE_BANK_SIZE - total + 1))
        bank, out = _noise_bank(), {}
        for (name, spec), size in zip(self.specs.items(), sizes):
            out[name] = bank[start:start + size].reshape(spec.height, spec.width, 3)
            start += size
        return out

    def measure(self) -> dict[str, np.ndarray]:
        t = sim_time(self.env)
        if self.rate_hz is not None and self._held is not None and t < self._next_capture - 1e-9:
            return {name: img.copy() for name, img in self._held.items()}  # frame hold between captures
        if self.rate_hz is not None:
            period = 1.0 / self.rate_hz
            while self._next_capture <= t + 1e-9:
                self._next_capture += period
        frames = render_views(self.env, self.specs, weather=self.weather)
        if self.noise is not None:
            noise = self._pixel_noise()
            frames = {name: self._noisy(name, frames[name], None if noise is None else noise[name])
                      for name in self.specs}
        self._held = frames
        return {name: img.copy() for name, img in frames.items()} if self.rate_hz is not None else frames


__all__ = ["ASPHALT", "CAMERA_NAMES", "MARKING", "NEAR_PLANE", "WINDSHIELD_HALF_WIDTH", "VEHICLE_HEIGHT", "CameraSpec",
           "Weather", "CameraNoise", "Cameras", "CamerasParams", "GroundTexture", "StaticScene", "build_scene",
           "ground_texture", "scene_of", "camera_rig", "render_view", "render_views"]
