"""SB3 callbacks: episode metrics to TensorBoard, periodic atomic checkpoints."""

from __future__ import annotations

from pathlib import Path

from stable_baselines3.common.callbacks import BaseCallback

LOGGED = {
    "left_turn": ("collision", "success", "time_to_exit_s", "min_ttc_s", "stopped", "mean_speed_mps"),
    "lane_keeping": ("lap_completed", "cte_mean_abs_m", "cte_max_abs_m", "lane_departures",
                     "steering_sign_changes_per_100m"),
}


class EpisodeMetricsCallback(BaseCallback):
    """Logs the ground-truth episode metrics (``info["episode_metrics"]``) as ``episode/<name>`` scalars, averaged
    over the episodes that ended since the last dump (one point per PPO rollout), e.g. collision rate."""

    def __init__(self, scenario: str) -> None:
        super().__init__()
        self.keys = LOGGED[scenario]

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            metrics = info.get("episode_metrics")
            if metrics:
                for key in self.keys:
                    if key in metrics and metrics[key] == metrics[key]:  # skip NaN (e.g. never exited)
                        self.logger.record_mean(f"episode/{key}", metrics[key])
        return True


class AtomicCheckpointCallback(BaseCallback):
    """Checkpoints at rollout boundaries, at least ``every`` env steps apart: ``latest.zip`` (policy, optimizer,
    step counter) and ``latest.rng`` (RNG states and the logger values not yet written to TensorBoard), both
    atomically. At a boundary the parameters, the step counter and the pending log values are consistent, so a
    resumed run repeats no update and loses no TensorBoard point.

    :meth:`save` may also be called mid-rollout (on SIGINT/SIGTERM): parameters do not change while a rollout is
    collected, so it saves the state of the last boundary and the half-collected rollout is simply redone."""

    def __init__(self, folder: Path, every: int) -> None:
        super().__init__()
        self.folder, self.every = Path(folder), int(every)
        self._boundary = 0
        self._pending: dict = {}
        self._last_save = None

    def _on_training_start(self) -> None:
        self._boundary = self._last_save = self.num_timesteps

    def _on_rollout_start(self) -> None:
        self._boundary = self.num_timesteps
        self._pending = {"name_to_value": dict(self.logger.name_to_value),
                         "name_to_count": dict(self.logger.name_to_count),
                         "name_to_excluded": dict(self.logger.name_to_excluded)}
        if self.every > 0 and self.num_timesteps - self._last_save >= self.every:
            self.save()

    def _on_step(self) -> bool:
        return True

    def save(self) -> None:
        from train.checkpoint import save_model_atomic, save_rng_state

        steps = self.model.num_timesteps
        self.model.num_timesteps = self._boundary
        try:
            save_rng_state(self.folder / "latest.rng", extra={"logger": self._pending})
            save_model_atomic(self.model, self.folder / "latest.zip")
        finally:
            self.model.num_timesteps = steps
        self._last_save = self._boundary
