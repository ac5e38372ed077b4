"""The runnable examples of the public docstrings (Gymnasium's style, ``>>> import gymnasium as gym ...``) run as
doctests in the fast suite: the sensor wrappers, the package and :func:`av_gym.api.make` (``gym.make`` with the
harness's keywords, a checkpoint's env) and :func:`av_gym.make.make_env`. An example whose output no longer
matches the code fails here."""

from __future__ import annotations

import doctest
import importlib
import inspect

import pytest

from av_gym.sensors.base import SensorWrapper

SENSOR_MODULES = ["av_gym.sensors.camera", "av_gym.sensors.detector", "av_gym.sensors.gnss", "av_gym.sensors.imu",
                  "av_gym.sensors.lidar", "av_gym.sensors.turn_signal"]
MODULES = ["av_gym", "av_gym.api", "av_gym.make", *SENSOR_MODULES]


@pytest.mark.parametrize("name", MODULES)
def test_the_examples_run(name: str):
    """Each module's examples pass, and it has at least one (a module whose examples were all lost fails)."""
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    tests = [t for t in finder.find(module, name) if t.examples]
    assert tests, f"{name} has no runnable example"
    for test in tests:
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of {name} failed (output above)"


def test_every_public_sensor_wrapper_has_an_example():
    """A sensor wrapper added to av_gym/sensors comes with its ``>>>`` example (run above)."""
    wrappers = {cls for name in SENSOR_MODULES for _, cls in inspect.getmembers(importlib.import_module(name),
                                                                                inspect.isclass)
                if issubclass(cls, SensorWrapper) and cls is not SensorWrapper and not cls.__name__.startswith("_")}
    assert len(wrappers) >= 6
    missing = sorted(cls.__name__ for cls in wrappers if ">>> " not in (cls.__doc__ or ""))
    assert not missing, f"sensor wrappers without a runnable example in their docstring: {missing}"
