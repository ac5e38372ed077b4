"""The console scripts ``av-gym-train`` and ``av-gym-eval`` (pyproject ``[project.scripts]``): ``python -m train``
and ``python -m eval`` from any folder.

Why not simply ``train.__main__:main``: this distribution installs the top-level packages ``conf``, ``agents``,
``train`` and ``eval``, names a user's own project may hold too (``conf/`` is Hydra's usual layout). When the
working folder is on ``sys.path`` (``python -m``, ``python -c``, ``PYTHONPATH=.``) its folders shadow ours: Hydra
then finds no ``conf`` module ("Primary config module 'conf' not found") and ``agents`` lacks ``Policy``. The entry
points here drop the working folder from ``sys.path`` (unless it is this checkout itself) and forget any module of
those names imported from elsewhere, before importing the command. This module sits above every other floor
(tests/test_imports.py): it imports the commands."""

from __future__ import annotations

import sys
from pathlib import Path

# the top-level packages this distribution installs besides av_gym
PACKAGES = ("conf", "agents", "train", "eval")
ROOT = Path(__file__).resolve().parents[1]
"""The folder holding av_gym/ and its sibling packages: the source checkout (editable install) or site-packages."""


def _ours(module) -> bool:
    """Whether an imported module comes from this distribution (a namespace package has no ``__file__``)."""
    where = getattr(module, "__file__", None) or next(iter(getattr(module, "__path__", [])), None)
    return where is not None and Path(where).resolve().is_relative_to(ROOT)


def prefer_installed_packages() -> None:
    """Make ``import conf`` / ``agents`` / ``train`` / ``eval`` find this distribution's packages, not same-named
    folders of the working folder."""
    cwd = Path.cwd().resolve()
    if cwd != ROOT:
        sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != cwd]
    for name in list(sys.modules):
        if name.split(".")[0] in PACKAGES and not _ours(sys.modules[name]):
            del sys.modules[name]


def train() -> None:
    """``av-gym-train [overrides]``: ``python -m train`` from any folder."""
    prefer_installed_packages()
    from train.__main__ import main

    main()


def evaluate() -> None:
    """``av-gym-eval [overrides]``: ``python -m eval`` from any folder."""
    prefer_installed_packages()
    from eval.__main__ import main

    main()
