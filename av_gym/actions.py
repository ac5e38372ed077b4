"""What an action must be: :func:`check_action`, called by everything that acts on an action before the
simulation does (the scenario envs, the AEB shield, :class:`~av_gym.wrappers.GoYieldActions`)."""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import error, spaces

from av_gym.errors import ConfigError


class InvalidAction(ConfigError, error.InvalidAction):
    """An action outside the env's ``action_space`` (a ``ValueError`` and Gymnasium's ``InvalidAction``)."""


def check_action(space: spaces.Space, action: Any) -> None:
    """Raise :class:`InvalidAction` (one line: the action, the space, what is wrong) unless ``action`` is in
    ``space``. Checked before anything acts on it: a NaN acceleration reached the shield's numba predictor and
    crashed the process, a discrete 3 became a bare ``KeyError``. Only checked, never
    converted: the env receives the action as given, so trajectories stay bit-identical."""
    problem = _action_problem(space, action)
    if problem:
        text = repr(action) if not isinstance(action, np.ndarray) else np.array2string(action, threshold=8)
        raise InvalidAction(f"action {text[:80]} is not in the action space {space}: {problem}")


def _action_problem(space: spaces.Space, action: Any) -> str | None:
    if isinstance(space, spaces.Discrete):
        if isinstance(action, np.ndarray) and action.shape == () and np.issubdtype(action.dtype, np.integer):
            action = action.item()
        if isinstance(action, (bool, np.bool_)) or not isinstance(action, (int, np.integer)):
            return f"expected an integer in [{space.start}, {space.start + space.n - 1}], got {type(action).__name__}"
        if not space.start <= int(action) < space.start + space.n:
            return f"expected an integer in [{space.start}, {space.start + space.n - 1}]"
        return None
    if isinstance(space, spaces.Box):
        if action is None or isinstance(action, (str, bytes, dict)):
            return f"expected an array of shape {space.shape}, got {type(action).__name__}"
        try:
            values = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            return f"expected an array of shape {space.shape}, got {type(action).__name__}"
        if values.shape != space.shape:
            return f"expected shape {space.shape}, got {values.shape}"
        if ((values >= space.low) & (values <= space.high)).all():  # one pass: NaN fails both comparisons
            return None
        return "not finite (NaN or inf)" if not np.isfinite(values).all() else "out of bounds"
    return None if space.contains(action) else "not contained"  # pragma: no cover - the scenarios use Discrete/Box


def check_actions(space: spaces.Space, actions: Any, n: int) -> None:
    """:func:`check_action` for a batch of ``n`` envs that share ``space`` (the batched engine's step): one action
    per env along the first axis, shape ``(n, *space.shape)``, where one number per env may also come as ``(n,)``
    or ``(n, 1)``. Vectorised, one pass over the batch (a step of 256 envs costs milliseconds, this microseconds);
    only a batch that fails is looked at env by env, so that the message names the first wrong env in
    :func:`check_action`'s words. Only checked, never converted."""
    values = np.asarray(actions) if not isinstance(actions, (str, bytes, dict)) else np.asarray(None)
    shapes = [(n, *space.shape)] + ([(n,), (n, 1)] if int(np.prod(space.shape)) == 1 else [])
    if values.shape not in shapes:
        raise InvalidAction(f"actions of shape {values.shape} for {n} envs: expected shape "
                            f"{' or '.join(str(s) for s in dict.fromkeys(shapes))}, one action of {space} per env")
    per_env = values.reshape(n, *space.shape)
    if _batch_in_space(space, per_env):
        return
    for i in range(n):
        problem = _action_problem(space, per_env[i])
        if problem:
            text = np.array2string(np.asarray(per_env[i]), threshold=8)
            raise InvalidAction(f"action {text[:80]} of env {i} is not in the action space {space}: {problem}")


def _batch_in_space(space: spaces.Space, per_env: np.ndarray) -> bool:
    """Whether every row of ``per_env`` (shape ``(n, *space.shape)``) is in ``space``, in one vectorised pass;
    False also for what it cannot decide at once (an object array), which is then checked env by env."""
    if isinstance(space, spaces.Discrete):
        if not np.issubdtype(per_env.dtype, np.integer):
            return False
        return bool(((per_env >= space.start) & (per_env < space.start + space.n)).all())
    if isinstance(space, spaces.Box):
        if per_env.dtype.kind not in "biuf":
            return False
        return bool(((per_env >= space.low) & (per_env <= space.high)).all())  # NaN fails both comparisons
    return False  # pragma: no cover - the scenarios use Discrete/Box
