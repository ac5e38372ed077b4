"""Dependencies run one way, floor by floor (docs/design.md, "Layers"): a module imports only from its own unit or
from units on a lower floor, so no import runs back up (``envs/batched_vec.py`` → ``make.py`` → ``envs``
and ``estimation/*_features.py`` → ``envs`` were two that did). Read from the source (every import statement, also
those inside functions), so a lazy import cannot hide an arrow."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("av_gym", "av_gym_sb3", "agents", "conf", "train", "eval", "av_gym_harness")

# unit → floor. A unit is a top-level package, or ``av_gym.<module or subpackage>``; ``av_gym`` itself is the
# package's __init__ (the Gymnasium ids). Units on one floor do not import each other.
FLOORS = {
    "av_gym.errors": 0, "av_gym.geometry": 0,                   # no av_gym imports but errors
    "av_gym.references": 0.5,                                   # where the shipped presets and agents lie
    "av_gym": 0.7,                                              # the package: ids, reference()
    "av_gym.params": 1, "av_gym.registry": 1, "av_gym.metrics": 1, "av_gym.atomic": 1, "av_gym.seeds": 1,
    "av_gym.actions": 1,                                        # what an action must be (envs, shields, wrappers)
    "av_gym.sim": 2,                                            # the simulator (highway-env fast paths, batched traffic)
    "av_gym.sensors": 3,                                        # sensor models, wrappers over any env
    "av_gym.estimation": 4,                                     # EKF, tracker, features from sensor readings
    "av_gym.envs": 5, "av_gym.shields": 5, "av_gym.wrappers": 5,  # scenarios; shields; action/observation wrappers
    "av_gym.presets": 5.5,                                      # the shipped presets, composed from their Params
    "av_gym.make": 6,                                           # config → env + sensors + shield
    "av_gym.batched": 7,                                        # the batched left turn (reuses all of the above)
    "av_gym.api": 8,                                            # the registered ids' entry points (gym.make/make_vec)
    "av_gym_sb3": 8.5,                                          # torch classes that saved models name (RL stack)
    "agents": 9,
    "conf": 10,
    "eval": 11,
    "train": 12,                                                # train evaluates (eval); eval never trains
    "av_gym_harness": 13,                                       # the console scripts: they start the commands
}
# third-party libraries that only the harness may use: the library (every av_gym unit) stays free of the RL stack,
# so that gym.make / gymnasium.make_vec load neither
RL_LIBRARIES = ("stable_baselines3", "torch")
RL_FLOOR = FLOORS["av_gym_sb3"]


def unit_of(module: str) -> str:
    """``av_gym.sensors.camera`` → ``av_gym.sensors``; ``agents.ppo`` → ``agents``."""
    parts = module.split(".")
    return parts[0] if parts[0] != "av_gym" or len(parts) == 1 else f"av_gym.{parts[1]}"


@functools.lru_cache(maxsize=None)
def import_nodes(path: Path) -> tuple[ast.Import | ast.ImportFrom, ...]:
    """Every import statement of one file (parsed once a process: the floor and the circle checks read the same
    ~140 files, ~2 s a pass)."""
    return tuple(node for node in ast.walk(ast.parse(path.read_text(), str(path)))
                 if isinstance(node, (ast.Import, ast.ImportFrom)))


def imported_modules(path: Path, root: Path) -> list[str]:
    names: list[str] = []
    for node in import_nodes(path):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for alias in node.names:  # ``from av_gym import make`` names a module, ``... import ENV_IDS`` a name
                module = f"{node.module}.{alias.name}"
                is_module = (root / Path(*module.split("."))).is_dir() or \
                    (root / Path(*module.split("."))).with_suffix(".py").exists()
                names.append(module if node.module == "av_gym" and is_module else node.module)
    return names


@functools.lru_cache(maxsize=None)
def edges(root: Path | None = None) -> dict[tuple[str, str], set[str]]:
    """(unit, imported unit or RL library) → the files making that import."""
    root = root or ROOT
    found: dict[tuple[str, str], set[str]] = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root)
            src = unit_of(".".join(rel.with_suffix("").parts).removesuffix(".__init__"))
            for name in imported_modules(path, root):
                top = name.split(".")[0]
                if top in PACKAGES:
                    dst = unit_of(name)
                elif top in RL_LIBRARIES:
                    dst = top
                else:
                    continue
                if dst != src:
                    found.setdefault((src, dst), set()).add(str(rel))
    return found


def import_picture() -> list[str]:
    """``unit → unit`` lines (floor order), the picture docs/design.md shows."""
    return [f"{s} → {d}" for s, d in sorted(edges(), key=lambda e: (FLOORS.get(e[0], 99), e[0], e[1]))]


def test_every_unit_has_a_floor():
    units = {s for s, _ in edges()} | {d for _, d in edges() if d not in RL_LIBRARIES}
    assert units - set(FLOORS) == set(), "give each new package a floor in FLOORS (and docs/design.md)"


def test_imports_only_go_down():
    wrong = {f"{s} → {d}": sorted(files) for (s, d), files in edges().items()
             if d not in RL_LIBRARIES and FLOORS.get(d, 99) >= FLOORS.get(s, -1)}
    assert wrong == {}, f"imports that do not go down a floor: {wrong}\n" + "\n".join(import_picture())


def test_rl_libraries_stay_above_the_simulator():
    wrong = {f"{s} → {d}": sorted(files) for (s, d), files in edges().items()
             if d in RL_LIBRARIES and FLOORS.get(s, 99) < RL_FLOOR}
    assert wrong == {}, f"stable_baselines3/torch imported by the library (av_gym): {wrong}"


def test_the_checker_sees_lazy_and_upward_imports(tmp_path):
    """The walker finds an import inside a function (how av_gym used to reach agents) and an import from a lower
    av_gym floor to a higher one (estimation → envs, how the turn features used to reach the env)."""
    for package in PACKAGES:
        (tmp_path / package).mkdir()
    (tmp_path / "av_gym" / "m.py").write_text("def f():\n    from agents.aeb import build_shield\n")
    (tmp_path / "av_gym" / "estimation").mkdir()
    (tmp_path / "av_gym" / "estimation" / "f.py").write_text("from av_gym.envs.left_turn import CONFLICT_POINT\n")
    found = edges(tmp_path)
    assert found[("av_gym.m", "agents")] == {"av_gym/m.py"}
    assert found[("av_gym.estimation", "av_gym.envs")] == {"av_gym/estimation/f.py"}
    assert FLOORS["av_gym.envs"] > FLOORS["av_gym.estimation"]


@pytest.mark.slow  # a fresh interpreter (~5 s idle): an end-to-end check
def test_the_library_loads_no_harness_and_no_rl_stack(tmp_path):
    """In a fresh interpreter, from a folder holding packages named like the harness's: ``gym.make`` with a
    sensors preset and a shield, a shipped agent's env by name and ``gymnasium.make_vec`` on the batch import
    none of conf/agents/train/eval, stable_baselines3 or torch."""
    import subprocess
    import sys

    for name in ("conf", "agents", "train", "eval"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "__init__.py").write_text(f"raise ImportError('the user folder\\'s {name} was imported')\n")
    (tmp_path / "conf" / "sensors").mkdir()
    code = (
        "import sys, gymnasium as gym, av_gym\n"
        "gym.make('av_gym/UnprotectedLeftTurn-v0', sensors='turn_perceived', shield='aeb').reset(seed=0)\n"
        "gym.make('av_gym/UnprotectedLeftTurn-v0', checkpoint='ppo_turn').reset(seed=0)\n"
        "gym.make_vec('av_gym/UnprotectedLeftTurn-v0', 2, sensors='turn_truth').reset(seed=0)\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('conf', 'agents', 'train', 'eval', 'stable_baselines3', 'torch'))\n"
        "print('loaded:', bad)\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "loaded: []" in res.stdout, res.stdout


# ------------------------------------------------------------------------------------------------ within a unit
def module_of(rel: Path) -> str:
    """``av_gym/shields/aeb.py`` → ``av_gym.shields.aeb``; a package's ``__init__.py`` is the package."""
    return ".".join(rel.with_suffix("").parts).removesuffix(".__init__")


def module_graph(root: Path | None = None) -> dict[str, set[str]]:
    """module → the modules of its own unit it imports (every import statement, those inside functions too). A
    ``from package import name`` points at the submodule when ``name`` is one, else at the package."""
    root = root or ROOT
    graph: dict[str, set[str]] = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            src = module_of(path.relative_to(root))
            graph.setdefault(src, set())
            for node in import_nodes(path):
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [f"{node.module}.{alias.name}" if _is_module(root, f"{node.module}.{alias.name}")
                             else node.module for alias in node.names]
                else:
                    continue
                graph[src] |= {n for n in names if n != src and n.split(".")[0] in PACKAGES and
                               unit_of(n) == unit_of(src)}
    return graph


def _is_module(root: Path, name: str) -> bool:
    path = root / Path(*name.split("."))
    return path.is_dir() or path.with_suffix(".py").exists()


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan): each holds at least one circle."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circle_inside_a_unit():
    """Two modules of one unit that import each other (even lazily) are one module in two files, or a registry
    filled from the wrong side: whoever reads one must read both."""
    assert import_cycles(module_graph()) == []


def test_the_circle_check_finds_a_planted_circle(tmp_path):
    for package in PACKAGES:
        (tmp_path / package).mkdir()
    (tmp_path / "eval" / "a.py").write_text("from eval.b import f\n")
    (tmp_path / "eval" / "b.py").write_text("def f():\n    from eval import c\n")
    (tmp_path / "eval" / "c.py").write_text("def g():\n    import eval.a\n")
    (tmp_path / "eval" / "d.py").write_text("from eval.a import f\n")  # into the circle, not part of it
    (tmp_path / "av_gym" / "shields").mkdir()
    (tmp_path / "av_gym" / "shields" / "x.py").write_text("from av_gym.shields.y import Y\n")
    (tmp_path / "av_gym" / "shields" / "y.py").write_text("Y = 1\n")
    assert import_cycles(module_graph(tmp_path)) == [["eval.a", "eval.b", "eval.c"]]


if __name__ == "__main__":
    print("\n".join(import_picture()))
