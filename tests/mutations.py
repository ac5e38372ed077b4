"""Each equivalence test relaxed from bit identity to a portable tolerance must still fail on a real
change. This script applies one small mutation at a time to the code under test, runs the tests that guard it, and
reports whether they failed (as they must), then restores the file. Not collected by pytest (no ``test_`` prefix);
run it by hand: ``python tests/mutations.py`` (a few minutes: each mutation recompiles its numba kernels)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# (file, original text, mutated text, what it models, tests that must fail)
MUTATIONS = [
    ("av_gym/sim/kernels.py", "acc = acc - acc_max * (d_star / d) ** 2.0", "acc = acc - acc_max * (d_star / d) ** 2.01",
     "a constant in the IDM kernel's interaction term",
     ["tests/test_kernels.py::test_idm_kernel_is_the_numpy_idm"]),
    ("av_gym/sim/kernels.py", "                if dist[e] > 0:\n", "                if dist[e] >= 0:\n",
     "`>` for `>=` in the collision kernel's separating-axis test",
     ["tests/test_kernels.py::test_collision_kernel_is_the_numpy_separating_axes"]),
    ("av_gym/sim/batched.py", "COMFORT_ACC_MAX, COMFORT_ACC_MIN, ACC_MAX = 6.0, -3.0, 6.0",
     "COMFORT_ACC_MAX, COMFORT_ACC_MIN, ACC_MAX = 6.1, -3.0, 6.0", "a changed IDM constant in the batched engine",
     # (the outcome test is not listed: a 0.1 m/s² change moves trajectories, which the two 5-s identity tests
     # see, but it does not move whole-episode outcomes at 24 seeds; that test is for the mutation below)
     ["tests/test_batched_sim.py::test_batched_matches_per_env_stack_for_5_s",
      "tests/test_batched_sim.py::test_batched_continuous_actions_match_per_env_stack_for_5_s"]),
    ("av_gym/batched/left_turn.py", "            terminated[rows] = crashed | arrived\n",
     "            terminated[rows] = crashed\n", "arrival no longer ends a batched episode",
     ["tests/test_batched_sim.py::test_batched_episodes_end_as_on_the_per_env_stack"]),
    ("av_gym/shields/kernels.py", "return x + extra * math.cos(h), y + extra * math.sin(h), h, max(j, 0)",
     "return x + extra * math.cos(h) * (1 + 1e-9), y + extra * math.sin(h), h, max(j, 0)",
     "a 1e-9 relative error in the shield's driven-path extrapolation",
     ["tests/test_aeb.py::test_driven_path_kernel_equals_the_numpy_reference"]),
    ("av_gym/sensors/kernels.py", "ranges[e, k] = slant if slant < max_range else max_range",
     "ranges[e, k] = slant * (1 + 1e-10) if slant < max_range else max_range",
     "a 1e-10 relative error in the LiDAR ranges", ["tests/test_sensor_kernels.py::test_cast_kernel_is_the_numpy_cast"]),
]


def main() -> int:
    bad = 0
    for rel, old, new, what, tests in MUTATIONS:
        path = ROOT / rel
        text = path.read_text()
        if text.count(old) != 1:
            print(f"SKIP {what}: the original text is not found once in {rel} (update this script)")
            bad += 1
            continue
        path.write_text(text.replace(old, new))
        try:
            for test in tests:  # each test on its own: every one of them must fail
                rc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:xdist", "-p",
                                     "no:cacheprovider", test], cwd=ROOT, capture_output=True, text=True).returncode
                ok = rc != 0
                bad += not ok
                print(f"{'caught' if ok else 'MISSED'}: {what} ({rel}) -> {test.split('::')[1]} "
                      f"{'failed' if ok else 'passed'}", flush=True)
        finally:
            path.write_text(text)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
