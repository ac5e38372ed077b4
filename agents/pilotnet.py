"""PilotNet (paper 001 Table 1, after Bojarski et al. 2016) in torch, its preprocessing, and a :class:`Policy` that
steers from the centre camera only, as the paper drives (digest 001 §2, §3).

Network (digest 001 §3.1–3.2; 252,219 trainable parameters, a test checks the count)::

    input 3×66×200 (YUV, normalised)
    conv 24@5×5 /2 → ELU → conv 36@5×5 /2 → ELU → conv 48@5×5 /2 → ELU      (31×98, 14×47, 5×22)
    conv 64@3×3 /1 → ELU → conv 64@3×3 /1 → ELU → dropout 0.5               (3×20, 1×18)
    flatten 1152 → dense 100 → ELU → dropout → dense 50 → ELU → dropout → dense 10 → ELU → dropout → dense 1

Preprocessing (the same function at training and at drive time):
    1. crop: drop the top ``crop_top`` rows (the sky above the horizon: building tops, tree crowns and poles that
       change from seed to seed and layout to layout and carry no lane information; paper 001 §5.5 "crop what
       training does not need") and resize back to 66×200 so the input is exactly the paper's. The camera already
       renders 66×200 with no bonnet in view, so nothing is cut at the bottom. With the default camera (70° FOV,
       8° pitch) the horizon is at row 12.5, hence ``crop_top = 12``.
    2. RGB → YUV with OpenCV's BT.601 formula (Y = .299R + .587G + .114B, U = .492(B − Y) + 128,
       V = .877(R − Y) + 128, saturated to [0, 255]); done in torch so that training can augment in RGB first.
    3. normalise: x / 127.5 − 1, so every channel lies in [−1, 1] (digest 001 §2: the paper normalises, the
       formula is not given).

Steering: one output, the normalised steering in [−1, 1] (+ = right, ±1 ↦ ±25°); clipped at drive time.
"""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import nn

INPUT_HEIGHT, INPUT_WIDTH = 66, 200
N_PARAMETERS = 252_219  # paper 001 Table 1 (with the two extraction errors corrected, digest 001 §3.1)
DEFAULT_CROP_TOP = 12  # rows above the horizon of the default camera (see module docstring)
FORMAT = "av_gym.pilotnet/1"  # tag of the checkpoint dict written by train/bc.py

# OpenCV's COLOR_RGB2YUV (BT.601, analogue YUV scaled to 8 bits); checked against cv2 in tests/test_pilotnet.py.
_RGB2YUV = torch.tensor([[0.299, 0.587, 0.114],
                         [-0.299 * 0.492, -0.587 * 0.492, 0.886 * 0.492],
                         [0.701 * 0.877, -0.587 * 0.877, -0.114 * 0.877]])
_YUV_OFFSET = torch.tensor([0.0, 128.0, 128.0])


class PilotNet(nn.Module):
    """The paper's CNN; ``forward`` takes (B, 3, 66, 200) normalised YUV and returns (B,) steering."""

    def __init__(self, dropout: float = 0.5) -> None:
        super().__init__()
        elu = nn.ELU
        self.features = nn.Sequential(
            nn.Conv2d(3, 24, 5, stride=2), elu(),
            nn.Conv2d(24, 36, 5, stride=2), elu(),
            nn.Conv2d(36, 48, 5, stride=2), elu(),
            nn.Conv2d(48, 64, 3, stride=1), elu(),
            nn.Conv2d(64, 64, 3, stride=1), elu(),
            nn.Dropout(dropout),
        )
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(1152, 100), elu(), nn.Dropout(dropout),
            nn.Linear(100, 50), elu(), nn.Dropout(dropout),
            nn.Linear(50, 10), elu(), nn.Dropout(dropout),
            nn.Linear(10, 1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x)).squeeze(-1)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


# ================================================================================================ preprocessing
def crop_resize(images: np.ndarray, crop_top: int = DEFAULT_CROP_TOP) -> np.ndarray:
    """Step 1: uint8 RGB (H, W, 3) or (N, H, W, 3) → the same with the top ``crop_top`` rows cut and the rest
    resized (bilinear) back to 66×200."""
    single = images.ndim == 3
    batch = images[None] if single else images
    if batch.ndim != 4 or batch.shape[-1] != 3:
        raise ValueError(f"expected RGB images (N, H, W, 3), got shape {images.shape}")
    if not 0 <= crop_top < batch.shape[1] - 1:
        raise ValueError(f"crop_top must be in [0, {batch.shape[1] - 2}], got {crop_top}")
    out = np.empty((len(batch), INPUT_HEIGHT, INPUT_WIDTH, 3), np.uint8)
    for i, img in enumerate(batch):
        img = img[crop_top:]
        out[i] = img if img.shape[:2] == (INPUT_HEIGHT, INPUT_WIDTH) else \
            cv2.resize(img, (INPUT_WIDTH, INPUT_HEIGHT), interpolation=cv2.INTER_LINEAR)
    return out[0] if single else out


def rgb_to_yuv(rgb: torch.Tensor) -> torch.Tensor:
    """Step 2: (B, 3, H, W) float RGB in [0, 255] → YUV in [0, 255] (OpenCV's formula, saturated)."""
    yuv = torch.einsum("ij,bjhw->bihw", _RGB2YUV.to(rgb), rgb) + _YUV_OFFSET.to(rgb)[None, :, None, None]
    return yuv.clamp(0.0, 255.0)


def normalise(yuv: torch.Tensor) -> torch.Tensor:
    """Step 3: [0, 255] → [−1, 1]."""
    return yuv / 127.5 - 1.0


def to_network_input(rgb: torch.Tensor) -> torch.Tensor:
    """Steps 2–3 on a float RGB batch (B, 3, 66, 200) in [0, 255]: what the network sees."""
    return normalise(rgb_to_yuv(rgb))


def preprocess(images: np.ndarray, crop_top: int = DEFAULT_CROP_TOP) -> torch.Tensor:
    """All three steps: uint8 RGB (H, W, 3) or (N, H, W, 3) camera images → (N, 3, 66, 200) network input."""
    cropped = crop_resize(np.asarray(images), crop_top)
    cropped = cropped[None] if cropped.ndim == 3 else cropped
    rgb = torch.from_numpy(np.ascontiguousarray(cropped)).permute(0, 3, 1, 2).float()
    return to_network_input(rgb)


# ================================================================================================ the driver
class PilotNetPolicy:
    """Steers from ``obs["cameras"]["centre"]`` only (paper 001: the centre camera at test time)."""

    def __init__(self, model: PilotNet, crop_top: int = DEFAULT_CROP_TOP, camera: str = "centre") -> None:
        self.model = model.eval()
        self.crop_top = int(crop_top)
        self.camera = camera

    def reset(self) -> None:
        pass

    @torch.no_grad()
    def steer(self, image: np.ndarray) -> float:
        """Normalised steering in [−1, 1] for one uint8 RGB image (H, W, 3)."""
        x = preprocess(image, self.crop_top).to(next(self.model.parameters()).device)  # a model trained on a GPU
        return float(np.clip(self.model(x)[0].item(), -1.0, 1.0))

    def act(self, obs: Any) -> np.ndarray:
        return np.array([self.steer(obs["cameras"][self.camera])], dtype=np.float32)


def load_checkpoint(path: str | Path) -> dict:
    """The checkpoint dict written by ``train.bc`` (tensors and plain values only: ``weights_only=True``, so
    loading it cannot run code, unlike a pickle)."""
    if Path(path).is_file() and Path(path).stat().st_size == 0:  # torch says only "EOFError"
        raise ValueError(f"{path} is empty (0 bytes): a copy or download that did not finish? Re-copy it or retrain")
    unreadable = (f"{path} is not a readable checkpoint: not a whole torch.save archive (truncated, or another "
                  f"kind of file); re-copy it or retrain")
    if Path(path).is_file() and not zipfile.is_zipfile(path):  # torch says "Weights only load failed" or "[Errno 22]"
        raise ValueError(unreadable)
    try:
        ckpt = torch.load(str(path), map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError) as exc:  # a damaged member of a zip whose directory is whole
        if not Path(path).is_file():
            raise
        raise ValueError(f"{unreadable} ({type(exc).__name__})") from None
    except pickle.UnpicklingError:
        raise ValueError(f"{path} holds Python objects besides tensors and plain values; refusing to unpickle it "
                         f"(weights_only=True)") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise ValueError(f"{path} is not a PilotNet checkpoint (expected format {FORMAT!r})")
    return ckpt


def _check_shapes(saved: dict, expected: dict, path: str | Path) -> None:
    """One line naming the first tensor that is missing, unexpected or of another shape (torch lists them all over
    many lines, which a one-line error cuts after its header)."""
    for key, tensor in expected.items():
        if key not in saved:
            raise ValueError(f"{path} is not this PilotNet's weights: it lacks {key!r} (shape "
                             f"{list(tensor.shape)})")
        got = getattr(saved[key], "shape", None)
        if got is None or tuple(got) != tuple(tensor.shape):
            raise ValueError(f"{path} holds weights of another network: {key!r} has shape "
                             f"{list(got) if got is not None else type(saved[key]).__name__}, PilotNet expects "
                             f"{list(tensor.shape)}")
    extra = sorted(set(saved) - set(expected))
    if extra:
        raise ValueError(f"{path} holds weights of another network: unexpected {extra[:3]}")


def load_policy(path: str | Path) -> PilotNetPolicy:
    ckpt = load_checkpoint(path)
    model = PilotNet()
    _check_shapes(ckpt["state_dict"], model.state_dict(), path)
    model.load_state_dict(ckpt["state_dict"])
    return PilotNetPolicy(model, crop_top=int(ckpt["preprocess"]["crop_top"]))


__all__ = ["PilotNet", "PilotNetPolicy", "N_PARAMETERS", "count_parameters", "crop_resize", "rgb_to_yuv",
           "normalise", "to_network_input", "preprocess", "load_checkpoint", "load_policy"]
