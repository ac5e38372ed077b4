"""The shipped presets of conf/ (``sensors/turn_perceived``, ``shield/aeb``, ``env/left_turn``) as the harness's
tools and tests ask for them. One implementation, the library's (:mod:`av_gym.presets`), which reads these yaml
files by path, so that ``gym.make(..., sensors=...)`` works in a project with a ``conf/`` of its own;
``tests/test_presets.py`` checks it against Hydra's own composition."""

from av_gym.presets import compose_group, preset_names

__all__ = ["compose_group", "preset_names"]
