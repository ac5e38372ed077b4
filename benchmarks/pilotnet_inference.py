"""PilotNet inference time per frame on one CPU core (a benchmark, not a test).

    python benchmarks/pilotnet_inference.py [--checkpoint checkpoints/reference/pilotnet/model.pt]
                                            [--frames 2000] [--threads 1]

Times, per camera frame, (a) the network alone on a preprocessed (1, 3, 66, 200) tensor and (b) the whole
``PilotNetPolicy.act`` as it runs in the loop (crop/resize, RGB→YUV, normalise, forward, clip), on real frames
from the centre camera of layout A. ``torch.set_num_threads(1)``; median and 95th percentile over ``--frames``
frames after a warm-up. Without a checkpoint the weights are random (timing does not depend on them).
"""

from __future__ import annotations

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

# a script in the checkout: the harness packages (conf, agents, train, eval) are the checkout's, beside this folder
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse
import platform
import time

import numpy as np
import torch


def main(argv=None) -> dict:
    p = argparse.ArgumentParser()
    p.add_argument("--checkpoint", default="checkpoints/reference/pilotnet/model.pt")
    p.add_argument("--frames", type=int, default=2000)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)

    from pathlib import Path

    from agents.pilotnet import PilotNet, PilotNetPolicy, load_policy, preprocess
    from av_gym.make import make_env
    from av_gym.sensors.camera import CameraSpec, render_view


    policy = load_policy(a.checkpoint) if Path(a.checkpoint).is_file() else PilotNetPolicy(PilotNet())
    env = make_env({"name": "lane_keeping"})  # every other field: its Params default
    env.reset(seed=0)
    frames = []
    for k in range(200):  # 200 distinct frames along the first 20 s of the lap, driven straight-ish
        frames.append(render_view(env, CameraSpec()))
        _, _, terminated, truncated, _ = env.step(np.array([0.0 if k < 110 else -0.45], np.float32))
        if terminated or truncated:  # off the road: the frames go on from a new start
            env.reset(seed=k)
    env.close()

    def timed(fn, n):
        for i in range(50):
            fn(i)
        t = np.empty(n)
        for i in range(n):
            t0 = time.perf_counter()
            fn(i)
            t[i] = time.perf_counter() - t0
        return 1e3 * np.median(t), 1e3 * np.percentile(t, 95)

    inputs = [preprocess(f, policy.crop_top) for f in frames]
    with torch.no_grad():
        net = timed(lambda i: policy.model(inputs[i % len(inputs)]), a.frames)
    full = timed(lambda i: policy.act({"cameras": {"centre": frames[i % len(frames)]}}), a.frames)
    res = {"network_ms_median": net[0], "network_ms_p95": net[1], "policy_ms_median": full[0],
           "policy_ms_p95": full[1], "threads": torch.get_num_threads(), "torch": torch.__version__,
           "cpu": platform.processor() or platform.machine()}
    print(f"PilotNet inference, {a.frames} frames, torch {torch.__version__}, {torch.get_num_threads()} thread(s), "
          f"{res['cpu']}:")
    print(f"  network only (1×3×66×200):         median {net[0]:.2f} ms, p95 {net[1]:.2f} ms "
          f"({1000 / net[0]:.0f} frames/s)")
    print(f"  policy.act (preprocess + network): median {full[0]:.2f} ms, p95 {full[1]:.2f} ms "
          f"({1000 / full[0]:.0f} frames/s)")
    return res


if __name__ == "__main__":
    main()
