"""The camera renderer of this commit against the one before the per-frame speed-ups (issue 18, second pass).

    .venv/bin/python docs/cameras/compare_fast_path.py [--steps 150] [--before 50eaf6e] [--out NAME.md]

(third pass, the compiled painter: ``--before 118f99e --out compiled_painter_comparison.md``)

Loads ``av_gym/sensors/camera.py`` as it was at ``--before`` (``git show``) beside the current module, drives
the same poses as ``compare_renderers.py`` (lap A and B with PID on the true CTE, the left turn with IDLE), renders
the three clean windshield frames with both, by day, in fog (80 m) and at night, and writes
``docs/cameras/fast_path_comparison.md``: per-pixel |difference| (largest channel, 0-255) statistics. The new
renderer is meant to draw the same pixels except where the old one filled consecutive pieces of one wall with a
single ``fillPoly`` (its seams), now one ``fillConvexPoly`` per piece.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import types
from pathlib import Path

import numpy as np

from av_gym.sensors.camera import CAMERA_NAMES, camera_rig, render_views

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_renderers import SCENARIOS, WEATHERS, poses  # noqa: E402

OUT = Path(__file__).resolve().parent


def load_before(commit: str) -> types.ModuleType:
    """``av_gym/sensors/camera.py`` at ``commit`` as a module of its own."""
    root = Path(__file__).resolve().parents[2]
    src = subprocess.run(["git", "show", f"{commit}:av_gym/sensors/camera.py"], cwd=root, check=True,
                         capture_output=True, text=True).stdout
    mod = types.ModuleType("camera_before")
    mod.__file__ = f"<{commit}:av_gym/sensors/camera.py>"
    sys.modules[mod.__name__] = mod  # dataclasses look their module up
    exec(compile(src, mod.__file__, "exec"), mod.__dict__)
    return mod


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--before", default="50eaf6e")
    parser.add_argument("--out", default="fast_path_comparison.md", help="file name in docs/cameras/")
    args = parser.parse_args()
    old = load_before(args.before)
    rig = camera_rig()
    rows = []
    for scenario, (env_id, config) in SCENARIOS.items():
        for wname, weather in WEATHERS.items():
            w_old = old.Weather(**weather.as_dict())
            diffs = []
            for env in poses(env_id, config, args.steps):
                a = render_views(env, rig, weather=weather)
                b = old.render_views(env, rig, weather=w_old)
                diffs += [np.abs(a[c].astype(np.int16) - b[c]).max(-1) for c in CAMERA_NAMES]
            d = np.stack(diffs)
            rows.append((scenario, wname, len(d), d.mean(), (d > 0).mean(), (d > 10).mean(), (d > 30).mean(),
                         int(d.max())))
            print(rows[-1], flush=True)
    lines = [f"Renderer of this commit vs `{args.before}`, clean frames, "
             f"{args.steps} steps per scenario, 3 cameras; difference per pixel = largest channel difference.", "",
             "| scenario | conditions | frames | mean abs diff | pixels differing | pixels > 10 | pixels > 30 | max |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {s} | {w} | {n} | {m:.4f} | {p0:.3%} | {p10:.3%} | {p30:.3%} | {mx} |"
              for s, w, n, m, p0, p10, p30, mx in rows]
    (OUT / args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
