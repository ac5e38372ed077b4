"""Safety shields: ``gymnasium`` wrappers that sit between any agent and the scenario and may override its action
(listed in :data:`av_gym.registry.SHIELDS`, chosen by the ``shield`` config group).

- :mod:`av_gym.shields.aeb` — the predictive AEB shield for the unprotected left turn: one wrapper class
  per decision logic (``paper``, ``improved``, ``standard``, :data:`~av_gym.shields.aeb.AEB_VARIANTS`), each with
  its own typed parameters.
- :mod:`av_gym.shields.predict` — its motion prediction and collision tests (pure numpy functions).
"""
