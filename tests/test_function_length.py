"""Functions read top to bottom: none longer than :data:`LIMIT` lines unless its ``def`` line (or the line above
it) says why with a ``# long:`` comment. Compiled numba kernels are exempt: a kernel is one loop nest that numba
compiles as a whole, and splitting it costs a call per element or a second kernel to keep in step."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("av_gym", "av_gym_sb3", "av_gym_harness", "agents", "train", "eval", "conf", "benchmarks")
LIMIT = 80
REASON = "# long:"


def _jitted(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    return any("jit" in ast.unparse(d) for d in node.decorator_list)


def long_functions(root: Path = ROOT, folders: tuple[str, ...] = FOLDERS) -> list[str]:
    """``path:line name (n lines)`` for each function over the limit without a reason."""
    found = []
    for folder in folders:
        for path in sorted((root / folder).rglob("*.py")):
            text = path.read_text()
            lines = text.splitlines()
            for node in ast.walk(ast.parse(text, str(path))):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) or _jitted(node):
                    continue
                length = node.end_lineno - node.lineno + 1
                first = node.decorator_list[0].lineno if node.decorator_list else node.lineno
                reason = REASON in lines[node.lineno - 1] or (first > 1 and REASON in lines[first - 2])
                if length > LIMIT and not reason:
                    found.append(f"{path.relative_to(root)}:{node.lineno} {node.name} ({length} lines)")
    return found


def test_no_function_is_long_without_a_reason():
    assert long_functions() == [], (f"functions over {LIMIT} lines: split them into named steps, or say why on "
                                    f"the def line ({REASON} ...)")


def test_the_check_finds_a_long_function_and_accepts_a_reason_or_a_kernel(tmp_path):
    (tmp_path / "pkg").mkdir()
    body = "".join(f"    x{i} = {i}\n" for i in range(LIMIT))
    (tmp_path / "pkg" / "m.py").write_text(
        f"def long_one():\n{body}\n"
        f"def explained():  {REASON} one table, row by row\n{body}\n"
        f"{REASON} the same, said above the def\n@staticmethod\ndef explained_above():\n{body}\n"
        f"@numba.njit(cache=True)\ndef kernel():\n{body}\n"
        f"def short():\n    return 1\n")
    assert long_functions(tmp_path, ("pkg",)) == [f"pkg/m.py:1 long_one ({LIMIT + 1} lines)"]
