"""The improved shield's release test counts a car that may set off only within ``setoff_horizon``
(ImprovedAEB._release_test: the set-off prediction's slices capped at setoff_horizon / step, as in _setoff_stop and
the batch's screen, tests/test_setoff_rows.py)."""

from __future__ import annotations

import dataclasses

from agents import AlwaysProceed
from av_gym.shields.aeb_improved import ImprovedAEB
from conftest import conf, rollout

SEED = 1215  # tests/test_aeb.py: an oncoming car stands in the box after moving; the set-off rule latches the ego


class _Seen(Exception):
    """Ends the episode once the latched decision has been taken apart."""


def test_a_car_setting_off_beyond_the_setoff_horizon_does_not_hold_the_brake(make, turn_cfg, monkeypatch):
    """Seed 1215 latched at the line by the set-off rule (3 s, the preset): at its first release test the car that
    may set off meets the ego 1.9 s ahead (release margin), nothing else does. With the release clock one slice short
    of ``release_hold``, the same decision holds the brake at a set-off horizon of 2.5 s and 3 s, and releases at
    1.5 s and 1 s, where that meeting lies beyond the cap. Without the cap every horizon holds."""
    original = ImprovedAEB._release_test
    held: dict[float, bool] = {}

    def take_apart(self, sc, ttc, setoff):
        if setoff is None or not self._latched:
            return original(self, sc, ttc, setoff)
        preset = self.p
        for horizon in (3.0, 2.5, 1.5, 1.0):
            self.p = dataclasses.replace(preset, setoff_horizon=horizon)
            self._latched, self._clear_for = True, preset.release_hold - preset.step
            held[horizon] = original(self, sc, ttc, setoff) is not None
        raise _Seen

    monkeypatch.setattr(ImprovedAEB, "_release_test", take_apart)
    env = make(turn_cfg, None, conf("shield", "aeb"))
    aeb = env.env
    assert isinstance(aeb, ImprovedAEB) and aeb.p.setoff_speed > 0 and aeb.p.setoff_horizon == 3.0  # the preset's
    try:
        rollout(env, AlwaysProceed(env.unwrapped.cruise_action()), seed=SEED)
    except _Seen:
        pass
    assert held == {3.0: True, 2.5: True, 1.5: False, 1.0: False}, held
