"""The install declares what the code imports (omegaconf and PIL were imported but undeclared), and the
declared ranges hold the versions installed here (the ones the suite ran with)."""

from __future__ import annotations

import ast
import sys
import tomllib
from importlib.metadata import packages_distributions, version
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from test_imports import import_nodes

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("av_gym", "av_gym_sb3", "av_gym_harness", "agents", "conf", "train", "eval")  # this repository's own
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def _requirements(extra: str | None = None) -> dict[str, Requirement]:
    lines = PROJECT["dependencies"] if extra is None else PROJECT["optional-dependencies"][extra]
    return {canonicalize_name(r.name): r for r in map(Requirement, lines)}


def third_party_imports(folders: tuple[str, ...]) -> dict[str, set[str]]:
    """Top-level module → files importing it, for every import (lazy ones included) that is neither the standard
    library nor this project's own packages nor a sibling test module."""
    ours = set(PACKAGES) | {"tests"} | {p.stem for p in (ROOT / "tests").glob("*.py")}
    found: dict[str, set[str]] = {}
    for folder in folders:
        for path in (ROOT / folder).rglob("*.py"):
            for node in import_nodes(path):  # parsed once a process, shared with test_imports.py
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for top in {n.split(".")[0] for n in names} - ours - set(sys.stdlib_module_names):
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def _undeclared(imports: dict[str, set[str]], declared: set[str]) -> dict[str, list[str]]:
    distributions = packages_distributions()
    missing = {}
    for module, files in imports.items():
        names = {canonicalize_name(d) for d in distributions.get(module, [module])}
        if not names & declared:
            missing[module] = sorted(files)
    return missing


def test_every_third_party_import_of_the_package_is_declared():
    imports = third_party_imports(PACKAGES)
    assert {"numpy", "omegaconf", "PIL", "torch"} <= set(imports)  # the scan sees lazy imports too
    assert _undeclared(imports, set(_requirements())) == {}


def test_every_third_party_import_of_the_tests_is_declared_with_the_test_extra():
    declared = set(_requirements()) | set(_requirements("test"))
    assert _undeclared(third_party_imports(("tests",)), declared) == {}


def test_the_declared_ranges_hold_the_installed_versions():
    """Every requirement bounded above (numpy<3, pandas<4 ...) and satisfied by what this suite runs with."""
    for extra in (None, "test"):
        for name, req in _requirements(extra).items():
            installed = version(name)
            assert req.specifier.contains(installed, prereleases=True), f"{name} {installed} outside {req}"
    unbounded = [name for name, req in _requirements().items() if not any(s.operator == "<" for s in req.specifier)]
    assert unbounded == ["rich"], unbounded  # rich: only SB3's progress bar uses it, no API of its own here
