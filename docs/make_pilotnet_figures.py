"""Figures of the PilotNet reference run for docs/pilotnet/ (issue 4).

    python docs/make_pilotnet_figures.py --run runs/<pilotnet train run> \
        --eval-a runs/eval/issue4-A --eval-b runs/eval/issue4-B

Writes ``docs/pilotnet/``: ``training_curves.png`` (TensorBoard loss/train and loss/val), ``augmented_samples.png``
(the first augmented training batch as logged to TensorBoard), ``steering_histogram.png`` (demonstration labels by
camera, before and after balancing), ``cte_A.png`` / ``cte_B.png`` (copies of eval's ``cte_all.png``).
"""

from __future__ import annotations

import argparse
import io
import shutil
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

OUT = Path(__file__).resolve().parent / "pilotnet"


def main(argv=None) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from train.bc import balance, load_demos, split_by_chunks

    p = argparse.ArgumentParser()
    p.add_argument("--run", type=Path, required=True, help="the train run folder (has tb/ and demos.npz)")
    p.add_argument("--eval-a", type=Path, default=None)
    p.add_argument("--eval-b", type=Path, default=None)
    a = p.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)

    ea = EventAccumulator(str(next((a.run / "tb").glob("events.out.tfevents.*"))), size_guidance={"images": 0})
    ea.Reload()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for tag in ("loss/train", "loss/val"):
        ev = ea.Scalars(tag)
        ax.plot([e.step + 1 for e in ev], [e.value for e in ev], "o-", label=tag)
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE (normalised steering²)")
    ax.set_title("PilotNet behaviour cloning: train (augmented) and validation loss", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "training_curves.png", dpi=110)
    plt.close(fig)

    from PIL import Image

    img = ea.Images("samples/augmented_rgb")[0]
    Image.open(io.BytesIO(img.encoded_image_string)).save(OUT / "augmented_samples.png")

    demos = load_demos(a.run / "demos.npz")
    rng = np.random.default_rng(0)
    val = split_by_chunks(demos["frame"], demos["lap"], 50, 0.2, rng)
    idx = np.flatnonzero(~val)
    kept, cap = balance(demos["steering"][idx], 25, None, 2.0, rng)
    bins = np.linspace(-1, 1, 26)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    for c, name in enumerate(("left", "centre", "right")):
        axes[0].hist(demos["steering"][demos["camera"] == c], bins=bins, histtype="step", lw=1.5, label=name)
    axes[0].set_title("labels by camera (all demonstrations)", fontsize=9)
    axes[0].legend(fontsize=8)
    axes[1].hist(demos["steering"][idx], bins=bins, alpha=0.4, label="training split")
    axes[1].hist(demos["steering"][idx][kept], bins=bins, histtype="step", lw=1.5, label=f"balanced (cap {cap})")
    axes[1].set_title("balancing: 25 bins capped", fontsize=9)
    axes[1].legend(fontsize=8)
    for ax in axes:
        ax.set_xlabel("steering label (normalised, + = right)")
    fig.tight_layout()
    fig.savefig(OUT / "steering_histogram.png", dpi=110)
    plt.close(fig)

    for name, folder in (("A", a.eval_a), ("B", a.eval_b)):
        if folder is not None and (folder / "cte_all.png").is_file():
            shutil.copy(folder / "cte_all.png", OUT / f"cte_{name}.png")
    print(f"figures in {OUT}")


if __name__ == "__main__":
    main()
