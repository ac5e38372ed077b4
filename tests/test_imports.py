"""Dependencies run one way: av_gym (envs, sensors, estimation, shields, metrics) ← agents ← conf ← train, eval,
and eval never imports train (issue 20). Read from the source (every import statement, also those inside
functions), so a lazy import cannot hide an arrow."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("av_gym", "agents", "conf", "train", "eval")
FORBIDDEN = {
    "av_gym": {"agents", "conf", "train", "eval"},
    "agents": {"conf", "train", "eval"},
    "conf": {"train", "eval"},
    "eval": {"train"},
    "train": set(),
}


def imports_of(package: str) -> dict[str, set[str]]:
    """Top-level package → the files of ``package`` that import it."""
    found: dict[str, set[str]] = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top in PACKAGES and top != package:
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def import_picture() -> list[str]:
    """``package → package`` lines, the picture the README's layout section shows."""
    return [f"{package} → {other}" for package in PACKAGES for other in sorted(imports_of(package))]


def test_imports_run_one_way():
    wrong = {(package, other): sorted(files) for package in PACKAGES
             for other, files in imports_of(package).items() if other in FORBIDDEN[package]}
    assert wrong == {}, f"imports against the direction: {wrong}\n" + "\n".join(import_picture())


def test_the_checker_sees_lazy_imports(tmp_path, monkeypatch):
    """The walker finds an import inside a function (how av_gym used to reach agents)."""
    pkg = tmp_path / "av_gym"
    pkg.mkdir()
    (pkg / "m.py").write_text("def f():\n    from agents.aeb import build_shield\n    return build_shield\n")
    monkeypatch.setattr(__import__(__name__), "ROOT", tmp_path)
    assert imports_of("av_gym") == {"agents": {"av_gym/m.py"}}


if __name__ == "__main__":
    print("\n".join(import_picture()))
