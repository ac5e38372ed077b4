"""The console scripts ``av-gym-train`` and ``av-gym-eval`` (pyproject ``[project.scripts]``): ``python -m train``
and ``python -m eval`` from any folder, with the harness this distribution ships.

Where the harness is: the repository keeps ``conf/``, ``agents/``, ``train/`` and ``eval/`` at its top (the
project's layout; ``python -m train`` in a checkout). An install does not put those four names on ``sys.path``:
they are the commonest names in ML projects, and a user's ``train.py`` or ``conf/`` would shadow them or be
shadowed by them. A wheel carries them inside this package (``av_gym_harness/conf``, ... copied by setup.py), an
editable install finds them in the checkout beside ``av_gym/``. Only the console scripts' own process puts that
folder first on ``sys.path``, drops the working folder (whose same-named folders would otherwise be found first)
and forgets any module of those names imported from elsewhere; the library (``import av_gym``) never imports
them. This package sits above every other floor (tests/test_imports.py): it starts the commands."""

from __future__ import annotations

import sys
from pathlib import Path

PACKAGES = ("conf", "agents", "train", "eval")
"""The harness's top-level packages."""

HERE = Path(__file__).resolve().parent


def harness_root() -> Path:
    """The folder holding the harness packages: this package's own folder in a wheel, else the checkout's root
    (the folder holding ``av_gym/`` and ``av_gym_harness/``)."""
    return HERE if (HERE / "train" / "__main__.py").is_file() else HERE.parent


def _ours(module, root: Path) -> bool:
    """Whether an imported module comes from ``root`` (a namespace package has no ``__file__``)."""
    where = getattr(module, "__file__", None) or next(iter(getattr(module, "__path__", None) or []), None)
    return where is not None and Path(where).resolve().is_relative_to(root)


def use_harness() -> Path:
    """Make ``import conf`` / ``agents`` / ``train`` / ``eval`` find this distribution's harness in this process,
    not same-named folders of the working folder; returns the harness root."""
    root = harness_root()
    cwd = Path.cwd().resolve()
    sys.path[:] = [str(root)] + [p for p in sys.path if Path(p or ".").resolve() not in (cwd, root)]
    for name in list(sys.modules):
        if name.split(".")[0] in PACKAGES and not _ours(sys.modules[name], root):
            del sys.modules[name]
    return root


def train() -> None:
    """``av-gym-train [overrides]``: ``python -m train`` from any folder."""
    use_harness()
    from train.__main__ import main

    main()


def evaluate() -> None:
    """``av-gym-eval [overrides]``: ``python -m eval`` from any folder."""
    use_harness()
    from eval.__main__ import main

    main()
