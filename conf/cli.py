"""The side tools' command line (``python -m eval.ccftap``, ``eval.tracking``, ``eval.sweep``, ``train.export``,
``benchmarks/*.py`` ...): argparse flags, written the way ``python -m train`` / ``python -m eval`` write values.

Why argparse and not Hydra for them: a side tool takes a few flags of its own (a CCFtap grid, a miss-rate list, a
folder to read) and composes no config groups; Hydra would add a run folder, ``.hydra/`` and its override grammar
for nothing. What the two share is the user's side of it:

- a list is written as Hydra writes one, ``--agents '[always_proceed,ppo_turn]'`` (the bare ``a,b`` is accepted
  too, and so are space-separated values where a flag takes several);
- a bad value is one line, ``error: <tool>: argument --ego: ...``, exit status 2, before anything is written;
- numbers are checked against the same bounds the Params declare where the tool passes them on.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any


class ToolParser(argparse.ArgumentParser):
    """argparse with the main commands' error convention: one ``error:`` line (no usage block), exit status 2."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(2, f"error: {self.prog}: {message}\n")


_NAMES = {int: "integer", float: "number", str: "name"}


def _kind_name(kind: Callable[[str], Any]) -> str:
    """The noun for a value of ``kind`` (``integer``, ``number``, ``name``; else the converter's name): one
    definition for the messages and the ``__name__`` argparse shows."""
    return _NAMES.get(kind, getattr(kind, "__name__", "value"))


def _one(kind: Callable[[str], Any]) -> str:
    """A single value's noun with its article: ``an integer``, ``a number``."""
    name = _kind_name(kind)
    return f"{'an' if name[:1].lower() in 'aeiou' else 'a'} {name}"


def _bounds(low: float | None, high: float | None) -> str:
    """What ``low``/``high`` (inclusive, either may be None) allow, for a message: ``in [1, 64]``, ``>= 0``, or ''."""
    if low is not None and high is not None:
        return f"in [{low}, {high}]"
    return f">= {low}" if low is not None else (f"<= {high}" if high is not None else "")


def _item(part: str, text: str, kind: Callable[[str], Any], low: float | None, high: float | None,
          choices: list | None) -> Any:
    """One item ``part`` of the list ``text`` converted by ``kind`` and checked; a bad one is one message naming it."""
    name = _kind_name(kind)
    try:
        value = kind(part)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a list of {name}s like [1,2], got {part!r} in {text!r}") from None
    if isinstance(value, float) and value != value:
        raise argparse.ArgumentTypeError(f"{part!r} is not a number")
    if (low is not None and value < low) or (high is not None and value > high):
        raise argparse.ArgumentTypeError(f"each value must be {_bounds(low, high)}, got {part!r}")
    if choices is not None and value not in choices:
        raise argparse.ArgumentTypeError(f"each value must be one of {choices}, got {part!r}")
    return value


def items(kind: Callable[[str], Any] = str, *, low: float | None = None, high: float | None = None,
          choices: list | None = None, unique: bool = False) -> Callable[[str], list]:
    """An argparse ``type`` for a list: ``[a,b]`` (Hydra's syntax) or ``a,b``; each item converted by ``kind`` and
    checked against ``low``/``high`` (inclusive) or ``choices``; with ``unique``, a value given twice (as converted:
    ``[0,0.0]``) is refused, for a list whose items are each run and counted once (a grid)."""

    def parse(text: str) -> list:
        body = text.strip()
        if body.startswith("[") and body.endswith("]"):
            body = body[1:-1]
        parts = [p.strip().strip("'\"") for p in body.split(",") if p.strip()]
        if not parts:
            raise argparse.ArgumentTypeError(f"expected a list like [a,b], got {text!r}")
        values = [_item(part, text, kind, low, high, choices) for part in parts]
        repeated = next((v for i, v in enumerate(values) if v in values[:i]), None) if unique else None
        if repeated is not None:
            shown = f"{repeated:g}" if isinstance(repeated, float) else repeated
            raise argparse.ArgumentTypeError(f"{shown} is given twice; give each value once")
        return values

    parse.__name__ = f"list of {_kind_name(kind)}s"
    return parse


def number(kind: Callable[[str], Any] = int, *, low: float | None = None,
           high: float | None = None) -> Callable[[str], Any]:
    """An argparse ``type`` for one number, checked against ``low``/``high`` (inclusive). A bad value is one message
    for one value, with what it may be: ``expected an integer in [1, 64], got '0'``."""
    expected = " ".join(filter(None, (_one(kind), _bounds(low, high))))

    def parse(text: str) -> Any:
        body = text.strip().strip("'\"")
        if "," in body or body.startswith("["):
            raise argparse.ArgumentTypeError(f"expected one value ({expected}), got {text!r}")
        try:  # a list item's checks; one message for a lone value, whatever the item's says
            return _item(body, text, kind, low, high, None)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None

    parse.__name__ = _kind_name(kind)
    return parse


class Extend(argparse.Action):
    """For ``nargs="+"`` with an :func:`items` type: ``--seeds 1 2``, ``--seeds [1,2]`` and ``--seeds 1,2`` give the
    same flat list."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, [v for group in values for v in group])


def out_folder_problem(path: str | Path, flag: str, cleared: bool = False) -> str | None:
    """Why folder ``path`` (given to ``flag``) cannot be made and written, in one line (``--out README.md/x``: a
    file where a folder must be; a folder inside the shipped references, read-only to every tool, or with
    ``cleared``, a folder the tool may empty, one that holds them: :func:`av_gym.references.shipped_problem`), or
    None; checked before the tool runs (:func:`av_gym.errors.folder_problem`)."""
    from av_gym.errors import folder_problem
    from av_gym.references import shipped_problem

    return shipped_problem(path, flag, cleared) or folder_problem(path, flag)


def held_outputs_problem(flag: str, folder: str | Path, names: Iterable[str], overwrite: bool, *,
                         given: str | Path | None = None, whose: str = "", elsewhere: str = "",
                         replace: str = "--overwrite") -> str | None:
    """The one refusal of every tool whose output folder already holds an earlier run's outputs (the files it
    writes, ``names``, in ``folder``), checked before any work: unless ``overwrite``, ``<flag>=<folder> already
    holds a, b<whose>; pick another <flag><elsewhere>, or replace them (it: one file) with <replace>``; else None
    (nothing held, or replacing them asked). ``given``: what ``flag`` was set to when ``folder`` is only where it
    writes beside (eval.tradeoff's ``--out`` names a figure, its sweep rows lie in its folder)."""
    held = [name for name in names if (Path(folder) / name).exists()]
    if not held or overwrite:
        return None
    where = f"{flag}={folder}" if given is None else f"{flag}={given}: its folder {folder}"
    return (f"{where} already holds {', '.join(held)}{whose}; pick another {flag}{elsewhere}, or replace "
            f"{'it' if len(held) == 1 else 'them'} with {replace}")


def out_file_problem(path: str, flag: str) -> str | None:
    """Why file ``path`` cannot be written: its folder cannot be made, or it is a folder itself; or None."""
    if Path(path).is_dir():
        return f"{flag}={path}: is a folder, not a file"
    parent = str(Path(path).parent)
    problem = out_folder_problem(parent, flag)
    return problem.replace(f"{flag}={parent}:", f"{flag}={path}:", 1) if problem else None


def out_figure_problem(path: str, flag: str, overwrite: bool | None = None) -> str | None:
    """:func:`out_file_problem` for a figure, checked before the work: also a suffix matplotlib cannot write
    (``--out t.csv`` was a traceback after the run), and unless ``overwrite``, a file already there (a figure or
    anyone's file is never replaced unasked; ``overwrite`` None: the tool has no ``--overwrite`` to offer)."""
    from matplotlib.backend_bases import FigureCanvasBase

    problem = out_file_problem(path, flag)
    if problem:
        return problem
    formats = sorted(FigureCanvasBase.get_supported_filetypes())
    suffix = Path(path).suffix.lstrip(".").lower()
    if suffix not in formats:
        return f"{flag}={path}: a figure's suffix must be one of {formats} (matplotlib's formats), got {suffix!r}"
    if not overwrite and Path(path).exists():
        remedy = " or give --overwrite" if overwrite is not None else ""
        return f"{flag}={path}: exists; choose another file{remedy} (a file is never replaced unasked)"
    return None
