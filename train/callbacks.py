"""SB3 callbacks: episode metrics to TensorBoard, periodic atomic checkpoints."""

from __future__ import annotations

from pathlib import Path

from stable_baselines3.common.callbacks import BaseCallback

from train.checkpoint import save_model_atomic

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
    """Every ``every`` env steps, writes ``<folder>/latest.zip`` atomically (temp file + rename)."""

    def __init__(self, folder: str | Path, every: int) -> None:
        super().__init__()
        self.folder, self.every = Path(folder), int(every)
        self._last = 0

    def _on_step(self) -> bool:
        if self.every > 0 and self.num_timesteps - self._last >= self.every:
            save_model_atomic(self.model, self.folder / "latest.zip")
            self._last = self.num_timesteps
        return True
