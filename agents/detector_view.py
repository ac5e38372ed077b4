"""What the car's detector can see: a place within its range and field of view and not behind a nearer road user the
car knows. One function shared by the planner's prior over unconfirmed cars (agents/track_prior.py) and its memory
of dropped tracks (agents/track_memory.py), kept apart from both so neither imports the other."""

from __future__ import annotations

import numpy as np

__all__ = ["in_view"]


def in_view(px: np.ndarray, py: np.ndarray, ego: np.ndarray, occluders: np.ndarray, present: np.ndarray,
            max_range: float, half_fov: float, occlusion: bool) -> np.ndarray:
    """Whether the places ``px``, ``py`` (m; (n, ...) or broadcastable to it) are within ``max_range`` (m) and the
    field of view ``half_fov`` (rad each side) of the ego poses ``ego`` (n, 3) ``[x, y, heading]``, and (with
    ``occlusion``) not behind a nearer occluder: ``occluders`` (n, M, 5) ``[x, y, heading, length, width]``,
    ``present`` (n, M); a place is behind one when its bearing is within the half-width the box shows across the
    line of sight and it is farther (the detector's view, its occlusion by the road users the car knows)."""
    extra = (1,) * (max(np.ndim(px), np.ndim(py)) - 1)
    col = lambda a: a.reshape((len(ego),) + extra)  # noqa: E731
    dx, dy = px - col(ego[:, 0]), py - col(ego[:, 1])
    r = np.hypot(dx, dy)
    bearing = np.arctan2(dy, dx)
    rel = (bearing - col(ego[:, 2]) + np.pi) % (2 * np.pi) - np.pi
    seen = (r <= max_range) & (np.abs(rel) <= half_fov)
    if occlusion and occluders.shape[1]:
        ox, oy = occluders[..., 0] - ego[:, 0, None], occluders[..., 1] - ego[:, 1, None]
        od = np.hypot(ox, oy)
        ob = np.arctan2(oy, ox)
        theta = occluders[..., 2] - ob
        # the half-width the box shows across the line of sight, as an angle at its distance
        half = 0.5 * (np.abs(occluders[..., 3] * np.sin(theta)) + np.abs(occluders[..., 4] * np.cos(theta)))
        ang = np.arctan2(half, np.maximum(od, 1e-6))
        for m in np.flatnonzero(present.any(axis=0)).tolist():
            diff = (bearing - col(ob[:, m]) + np.pi) % (2 * np.pi) - np.pi
            hidden = (np.abs(diff) <= col(ang[:, m])) & (r > col(od[:, m]))
            seen = seen & ~(hidden & col(present[:, m]))
    return seen
