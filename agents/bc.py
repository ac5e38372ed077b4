"""PilotNet's agent kind (``agent.kind: pilotnet``): its settings, :class:`PilotNetParams` (every field of
``conf/agent/pilotnet.yaml``: demonstrations, balancing, preprocessing, augmentation, training), and how a trained
checkpoint (``model.pt``) is loaded. The behaviour-cloning pipeline that reads these settings is
:mod:`train.bc`; the network, its preprocessing and the driving policy are :mod:`agents.pilotnet`.

Kept free of torch and OpenCV imports: the config checker and Hydra's defaults (``agent_kind/pilotnet``) read the
Params without loading either.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from agents.registry import AgentKind, AgentParams
from av_gym.errors import ConfigError
from av_gym.params import SEED_MAX, param


@dataclass(frozen=True)
class PilotNetParams(AgentParams):
    """Behaviour cloning of PilotNet (paper 001) from a pure-pursuit expert on three cameras; drives from the centre
    camera only. Every choice is explained in train/bc.py's docstring."""

    kind: Literal["pilotnet"] = param("pilotnet")
    name: str = param("pilotnet")
    scenarios: tuple[str, ...] = param(("lane_keeping",))
    sensors: str | None = param("cameras", doc="trained and evaluated on conf/sensors/cameras.yaml (eval builds a "
                                               "camera env for it)")
    # demonstrations
    demos: str | None = param(None, doc="a demos.npz from an earlier run (runs/<run>/demos.npz): reuse it instead "
                                        "of collecting")
    demo_laps: int = param(8, "laps", ge=1, doc="laps of the training layout A, env seeds demo_seed.. (eval uses "
                                                "1000+)")
    demo_seed: int = param(0, ge=0, le=SEED_MAX, doc="lap i uses env seed demo_seed + i")
    demo_max_steps: int | None = param(None, "steps", ge=1, doc="cap on steps per lap (tests); null = whole lap")
    lookahead: float = param(6.0, "m", gt=0, doc="pure-pursuit lookahead of the expert (slip-compensated)")
    perturb_std: float = param(0.15, ge=0, doc="OU steering perturbation, stationary std (normalised steering), "
                                               "for recovery data")
    perturb_tau: float = param(0.5, "s", gt=0, doc="its correlation time")
    side_labels: Literal["expert", "geometric"] = param(
        "expert", doc="expert: the command at the displaced pose | geometric: +- atan(d / recovery_distance)")
    recovery_distance: float = param(10.0, "m", gt=0, doc="for side_labels=geometric")
    # balancing (25-bin histogram, cap per bin)
    bins: int = param(25, ge=1, doc="histogram bins over [-1, 1]")
    bin_cap: int | None = param(None, "samples", ge=1, doc="per bin; null = cap_factor x median non-empty bin")
    cap_factor: float = param(2.0, gt=0, doc="see bin_cap")
    # preprocessing
    crop_top: int = param(12, "rows", ge=0, le=40, doc="sky rows cropped before resizing back to 66x200 (the "
                                                       "default camera's horizon is at row 12.5)")
    # augmentation
    flip_p: float = param(0.5, ge=0, le=1, doc="horizontal flip, label negated")
    shift_px: float = param(15.0, "px", ge=0, doc="horizontal shift +-, read as a yaw, label corrected by the "
                                                  "expert's sensitivity")
    vshift_px: float = param(3.0, "px", ge=0, doc="vertical shift +- (label unchanged)")
    rotate_deg: float = param(3.0, "deg", ge=0, doc="roll +- (label unchanged)")
    brightness: float = param(25.0, "8-bit", ge=0, doc="exposure offset, uniform +-")
    contrast: float = param(0.25, ge=0, le=0.99, doc="contrast about mid-grey, uniform 1 +- this")
    gain: float = param(0.15, ge=0, le=0.99, doc="per-image gain, uniform 1 +- this")
    pixel_noise: float = param(10.0, "8-bit", ge=0, doc="Gaussian pixel noise sigma, uniform in [0, this] per "
                                                        "image (camera: 3 by day; 'heavy' 8)")
    # conditions the cameras model, recreated on the clean demonstrations with the camera's equations
    night_p: float = param(0.25, ge=0, le=1, doc="share of images made night (ambient 0.3-0.5, headlight pools, "
                                                 "gamma 1.5-2.2)")
    night_pixel_noise: float = param(16.0, "8-bit", ge=0, doc="their pixel noise sigma up to this (camera: 12 at "
                                                              "night)")
    fog_p: float = param(0.25, ge=0, le=1, doc="share of images in fog, visibility log-uniform in "
                                               "[fog_min_m, fog_max_m]")
    fog_min_m: float = param(40.0, "m", gt=0, doc="see fog_p")
    fog_max_m: float = param(300.0, "m", gt=0, doc="see fog_p")
    blur_p: float = param(0.25, ge=0, le=1, doc="share of images blurred (Gaussian sigma up to blur_max_px, one "
                                                "sigma per batch)")
    blur_max_px: float = param(1.2, "px", ge=0, doc="see blur_p")
    # training (paper 001: Adam, lr 0.001, batch 100; MSE)
    learning_rate: float = param(1.0e-3, gt=0, doc="Adam step (paper 001)")
    batch_size: int = param(100, ge=1, doc="paper 001")
    epochs: int = param(8, ge=1, doc="max; the best validation epoch is usually the 2nd-4th")
    patience: int = param(3, "epochs", ge=1, doc="early stopping on the validation MSE")
    val_fraction: float = param(0.2, gt=0, lt=1, doc="held out by contiguous val_chunk_s pieces of driving")
    val_chunk_s: float = param(5.0, "s", gt=0, doc="see val_fraction (neighbouring frames are near duplicates)")
    dropout: float = param(0.5, ge=0, le=0.99, doc="paper 001's")
    closed_loop_laps: int = param(0, "laps", ge=0, doc="per epoch: laps of layout A (unseen training seeds "
                                                       "demo_seed+demo_laps+j, camera noise on) driven and logged to "
                                                       "TensorBoard")
    torch_threads: int = param(2, ge=1, doc="torch threads while training")
    device: Literal["cpu", "cuda", "auto"] = param("cpu", doc="torch device of the network while training (the "
                                                              "augmentation stays on the CPU, same random stream); "
                                                              "auto: cuda when available")
    seed: int | None = param(None, ge=0, le=SEED_MAX, doc="null: the run's seed")

    def relations(self) -> list[str]:
        found = super().relations()
        if not self.fog_min_m <= self.fog_max_m:
            found.append(f"@fog_min_m and @fog_max_m must satisfy 0 < fog_min_m <= fog_max_m, got "
                         f"{self.fog_min_m!r}, {self.fog_max_m!r}")
        if self.demos is not None and not Path(self.demos).is_file():
            found.append(f"@demos: no such file {self.demos!r} (a demos.npz written by an earlier run)")
        return found


class PilotNetAgent(AgentKind):
    """Trained by :func:`train.bc.train_pilotnet`; ``model.pt`` holds tensors and plain values only."""

    Params = PilotNetParams
    checkpoint = "model.pt"

    @classmethod
    def load(cls, model_path: Path, env: Any) -> Any:
        from agents.pilotnet import load_policy

        space = getattr(env.observation_space, "spaces", {}).get("cameras")
        if space is None or "centre" not in space.spaces:
            raise ConfigError(f"checkpoint {str(model_path)!r} (PilotNet) drives from obs['cameras']['centre']; this "
                              f"env gives {list(getattr(env.observation_space, 'spaces', {}))}; use sensors=cameras")
        try:
            return load_policy(model_path)  # torch.load(weights_only=True): tensors and plain values only
        except (ValueError, RuntimeError, EOFError, OSError, KeyError) as exc:  # torch's on a truncated/corrupt file
            raise ConfigError(f"checkpoint {str(model_path)!r}: {(str(exc).splitlines() or [type(exc).__name__])[0]}") \
                from None
