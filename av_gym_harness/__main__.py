"""``python -m av_gym_harness <module> [args]``: a side tool of the harness (``eval.results_page``,
``eval.interventions``, ``train.export`` ...) from an installed wheel, where ``python -m eval.results_page`` finds no
``eval``: the harness travels inside this package (:func:`av_gym_harness.use_harness`), and only the console
scripts ``av-gym-train`` / ``av-gym-eval`` put it on ``sys.path``. The module runs as ``python -m <module>`` would
in a checkout, with the same arguments, from any folder (a folder of the user's named ``eval/`` or ``train/`` is not
imported instead)."""

from __future__ import annotations

import importlib.util
import runpy
import sys

from av_gym_harness import PACKAGES, use_harness

USAGE = "python -m av_gym_harness <module> [args]"


def runnable_problem(name: str) -> str | None:
    """Why ``python -m <name>`` cannot run the harness module ``name`` (it does not exist; it is a package without a
    ``__main__``, where runpy ends in an ImportError traceback: ``conf``, ``agents``), or None. Imports ``name``'s
    parent packages (what finding it takes), never ``name`` itself."""
    try:
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations is not None:  # a package runs its __main__
            return None if importlib.util.find_spec(f"{name}.__main__") is not None else \
                (f"the harness's {name!r} is a package with nothing to run (no {name}.__main__); name a module of "
                 f"it, e.g. eval.results_page, train.export")
    except ImportError:  # a parent that is no package (eval.results_page.x)
        spec = None
    return None if spec is not None else f"the harness has no module {name!r}"


def main(argv: list[str] | None = None) -> int:
    """Run the harness module ``argv[0]`` with the arguments after it; 2 and one line when it is not one."""
    argv = sys.argv[1:] if argv is None else argv
    name = argv[0] if argv else ""
    if name.split(".")[0] not in PACKAGES:
        print(f"error: {USAGE}: the module must be one of the harness's ({', '.join(PACKAGES)}: e.g. "
              f"eval.results_page, train.export), got {name or 'none'!r}", file=sys.stderr)
        return 2
    use_harness()
    problem = runnable_problem(name)
    if problem:
        print(f"error: {USAGE}: {problem}", file=sys.stderr)
        return 2
    sys.argv = [name, *argv[1:]]
    runpy.run_module(name, run_name="__main__", alter_sys=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
