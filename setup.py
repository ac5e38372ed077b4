"""Packaging: what a wheel carries besides the ``av_gym`` and ``av_gym_harness`` packages (pyproject.toml holds
the rest). Why a custom ``build_py``: the repository keeps the harness (``conf/``, ``agents/``, ``train/``,
``eval/``) and the reference agents (``checkpoints/reference/``) at its top, and a wheel must carry them without
installing those generic names as top-level modules (docs/design.md, "Packaging"). setuptools maps files into a
package only from inside it, so the copies into the build folder are made here:

- ``av_gym/_shipped/conf/**.yaml`` and ``av_gym/_shipped/reference/``: the presets and agents the library reads
  by path (:mod:`av_gym.references`);
- ``av_gym_harness/{conf,agents,train,eval}/``: the harness the console scripts run (:mod:`av_gym_harness`).

An editable install copies nothing: both find the checkout's own folders."""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
HARNESS = ("conf", "agents", "train", "eval")
SKIP = shutil.ignore_patterns("__pycache__", "*.pyc", ".lock", "*.tmp")


class BuildWithShippedData(build_py):
    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        build = Path(self.build_lib)
        shipped = build / "av_gym" / "_shipped"
        shutil.rmtree(shipped, ignore_errors=True)
        shutil.copytree(ROOT / "conf", shipped / "conf", ignore=shutil.ignore_patterns("*.py", "__pycache__"))
        shutil.copytree(ROOT / "checkpoints" / "reference", shipped / "reference", ignore=SKIP)
        for name in HARNESS:
            target = build / "av_gym_harness" / name
            shutil.rmtree(target, ignore_errors=True)
            shutil.copytree(ROOT / name, target, ignore=SKIP)


setup(cmdclass={"build_py": BuildWithShippedData})
