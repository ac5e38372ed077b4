"""SB3 callbacks: episode metrics to TensorBoard, periodic evaluation on fixed seeds (best checkpoint, videos),
hyperparameters and a custom-scalars layout, periodic atomic checkpoints."""

from __future__ import annotations

import csv
import io
import math
import json
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

LOGGED = {
    "left_turn": ("collision", "success", "time_to_exit_s", "min_ttc_s", "stopped", "mean_speed_mps",
                  "intervention", "interventions", "override_fraction"),
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


def steps_text(decisions: int, action_repeat: int = 1) -> str:
    """SB3's step counter (``num_timesteps``: agent decisions, summed over the envs) in words: ``"N env steps"``
    when each decision is one env step, else ``"N decisions (M env steps)"`` (``agent.action_repeat`` env steps per
    decision: 5 on the left turn)."""
    if action_repeat == 1:
        return f"{decisions} env steps"
    return f"{decisions} decisions ({decisions * action_repeat} env steps)"


class AtomicCheckpointCallback(BaseCallback):
    """Checkpoints at rollout boundaries, at least ``every`` env steps apart (SB3 counts decisions: each is
    ``action_repeat`` env steps, converted here and only here): ``latest.zip`` (policy, optimizer, step counter, and
    inside it the RNG states and the logger values not yet written to TensorBoard), atomically. At a boundary the
    parameters, the step counter and the pending log values are consistent, so a resumed run repeats no update and
    loses no TensorBoard point.

    On SIGINT/SIGTERM (:meth:`interrupt`, installed by :func:`train.ppo.learn`): during a rollout the parameters are
    those of the last boundary, so :meth:`save` saves that boundary (unless already saved) and the half-collected
    rollout is redone; during an update (from a rollout's end to the next one's start: SB3's log dump and
    ``train()``) the parameters and Adam's moments are part-way, so the stop waits for the update to end and the
    next boundary is saved (a second signal stops at once and keeps the last ``latest.zip``). The RNG states saved
    are those taken at the boundary (:meth:`_at_boundary`), not the later ones a half-collected rollout has advanced:
    a resume from a checkpoint written mid-rollout draws what a resume from one written at the boundary would.
    :attr:`saved_at` is the step ``latest.zip`` holds (None: none yet)."""

    def __init__(self, folder: Path, every: int, action_repeat: int = 1) -> None:
        super().__init__()
        self.folder, self.every, self.repeat = Path(folder), int(every), int(action_repeat)
        self._boundary = 0
        self._pending: dict = {}
        self._rng: dict = {}  # the global RNG states at the boundary (train.checkpoint.rng_state)
        self._last_save = 0
        self._updating = False  # between a rollout's end and the next one's start: parameters part-way
        self._stop: int | None = None  # the signal whose stop waits for the update in progress to end
        self.saved_at: int | None = None

    def _on_training_start(self) -> None:
        from train.checkpoint import rng_state

        self._boundary = self._last_save = self.num_timesteps
        self._rng = rng_state()
        self.saved_at = self.num_timesteps if (self.folder / "latest.zip").is_file() else None  # a resume's

    def _at_boundary(self) -> None:
        """The consistent state to save from now on: this step, the log values the last update left pending, the
        RNG states (the rollout that starts now draws from them; a mid-rollout save must not take its later ones)."""
        from train.checkpoint import rng_state

        self._updating = False
        self._boundary = self.num_timesteps
        self._rng = rng_state()
        self._pending = {"name_to_value": dict(self.logger.name_to_value),
                         "name_to_count": dict(self.logger.name_to_count),
                         "name_to_excluded": dict(self.logger.name_to_excluded)}
        if self._stop is not None:  # a signal came during the update that has just ended
            self.save()
            raise KeyboardInterrupt

    def _on_rollout_start(self) -> None:
        self._at_boundary()
        if self.every > 0 and (self.num_timesteps - self._last_save) * self.repeat >= self.every:
            self.save()

    def _on_rollout_end(self) -> None:
        self._updating = True  # SB3 dumps the logs and runs train() before the next rollout starts

    def _on_training_end(self) -> None:
        self._at_boundary()  # after the last update: a signal during the final evaluation saves this state

    def _on_step(self) -> bool:
        return True

    def interrupt(self, signum: int, frame) -> None:
        """SIGINT/SIGTERM handler: KeyboardInterrupt now, or, the first time during an update, at the next
        boundary (after saving it)."""
        if self._updating and self._stop is None:
            self._stop = signum
            print("[train] signal received during a PPO update: stopping when it ends, at the next rollout "
                  "boundary (a second signal stops now and keeps the last checkpoint)", flush=True)
            return
        raise KeyboardInterrupt

    def save(self) -> bool:
        """Save the last boundary's state to ``latest.zip``; False (nothing written) during an update, whose
        parameters are part-way. A boundary already saved is not written again (``latest.zip`` already holds it)."""
        from train.checkpoint import save_model_atomic

        if self._updating:
            return False
        if self.saved_at == self._boundary:
            return True
        steps = self.model.num_timesteps
        self.model.num_timesteps = self._boundary
        try:  # the RNG states inside latest.zip: one file, replaced at once (a pair of files could tear)
            # the boundary's RNG states replace the current ones in the saved record (rng_state: extra wins)
            save_model_atomic(self.model, self.folder / "latest.zip", rng_extra={**self._rng, "logger": self._pending})
            stale = self.folder / "latest.rng"  # an older run's: the zip's own states win, and it would mislead
            if stale.exists():
                stale.unlink()
        finally:
            self.model.num_timesteps = steps
        self._last_save = self.saved_at = self._boundary
        return True


class FiniteGuard(BaseCallback):
    """Stops training with :class:`av_gym.errors.TrainingDiverged` (one line) when a loss or a parameter is NaN or
    infinite, before the next rollout, and so before :class:`AtomicCheckpointCallback` could overwrite the last good
    ``latest.zip`` with it (this callback must come first in the list). Checked once per rollout (after each update),
    a few microseconds per parameter tensor.

    ``learning_rate``: the configured one, named in the message when it is the likely cause; ``init_lr``: the
    behaviour-cloning one (``agent.init_lr``), when cloning ran with its own."""

    def __init__(self, learning_rate: float, checkpoint: Path | None = None, init_lr: float | None = None) -> None:
        super().__init__()
        self.learning_rate, self.checkpoint = float(learning_rate), checkpoint
        self.init_lr = None if init_lr is None else float(init_lr)

    def _on_training_start(self) -> None:
        if self.init_lr is None:
            self.check("the initial (cloned) policy")
        else:
            self.check("the initial (cloned) policy", ("agent.init_lr", self.init_lr))

    def _on_rollout_start(self) -> None:
        self.check("the last PPO update")

    def _on_step(self) -> bool:
        return True

    def problem(self) -> str | None:
        """What is not finite: a logged training loss, or a parameter (by name); None if all is finite."""
        import math

        for key, value in self.logger.name_to_value.items():
            if key.startswith("train/") and isinstance(value, float) and not math.isfinite(value):
                return f"{key} = {value}"
        return nonfinite_parameter(self.model.policy)

    def check(self, after: str, lr: tuple[str, float] | None = None) -> None:
        found = self.problem()
        if found:
            raise self.diverged(found, after, lr)

    def diverged(self, found: str, after: str, lr: tuple[str, float] | None = None):
        name, value = lr or ("agent.learning_rate", self.learning_rate)
        return diverged_error(found, after, name, value, self.checkpoint, self.num_timesteps)


def diverged_error(found: str, after: str, lr_name: str, lr: float, checkpoint: Path | None = None,
                   steps: int | None = None):
    """The one-line :class:`av_gym.errors.TrainingDiverged` for ``found`` (what is not finite), naming the likely
    cause (the learning rate ``lr_name`` when it is large) and whether ``checkpoint`` (the last good one) exists."""
    from av_gym.errors import TrainingDiverged

    if lr > 1e-2:  # Adam on these networks: 1e-4..1e-3 (conf/agent/); 1e-2 is already aggressive
        cause = f"{lr_name}={lr:g} is far above PPO's usual 1e-4..1e-3: lower it"
    else:
        cause = (f"a reward or observation that is not finite, or steps too large for this problem: lower "
                 f"{lr_name} ({lr:g}) or agent.max_grad_norm")
    kept = (f"the last good checkpoint, {checkpoint}, is kept" if checkpoint and Path(checkpoint).is_file()
            else "no checkpoint had been written yet")
    at = f" at {steps} steps" if steps is not None else ""
    return TrainingDiverged(f"training diverged{at}: {found} after {after}; likely cause: {cause}; {kept}")


def raise_if_diverged(exc: BaseException, policy, after: str, lr_name: str, lr: float) -> None:
    """Called with an exception from torch (a distribution refusing NaN logits, say): if ``policy`` has a
    non-finite parameter, that is what happened; raise the one-line :class:`TrainingDiverged` instead."""
    from av_gym.errors import ConfigError

    found = None if isinstance(exc, ConfigError) else nonfinite_parameter(policy)
    if found:
        raise diverged_error(found, after, lr_name, lr) from None


def nonfinite_parameter(policy) -> str | None:
    """``"<name> has NaN/inf values"`` for the first policy parameter that is not finite, else None."""
    import torch

    for name, param in policy.named_parameters():
        if not bool(torch.isfinite(param).all()):
            return f"parameter {name} has NaN/inf values"
    return None


def score(scenario: str, metrics: dict) -> float:
    """One number per evaluation, higher is better, for keeping the best checkpoint: success rate minus collision
    rate on the left turn (a collision costs as much as a success earns); laps completed minus mean |CTE| (m) on
    lane keeping."""
    if scenario == "left_turn":
        return float(metrics["success"] - metrics["collision"])
    return float(metrics["lap_completed"] - metrics["cte_mean_abs_m"])


def dump_prefix(logger, prefix: str, step: int) -> None:
    """Write the logger's pending values whose names start with ``prefix`` at ``step`` and keep the others
    pending. SB3's EvalCallback dumps everything at an evaluation; here that would write PPO's ``train/*`` values
    a rollout early and twice at the last step, so the others wait for SB3's own dump as before."""
    stores = (logger.name_to_value, logger.name_to_count, logger.name_to_excluded)
    held = [{k: v for k, v in store.items() if not k.startswith(prefix)} for store in stores]
    for store, keep in zip(stores, held):
        for k in keep:
            del store[k]
    logger.dump(step)  # writes the prefix's values and clears every store
    for store, keep in zip(stores, held):
        store.update(keep)


def tensorboard_writer(logger):
    """The ``SummaryWriter`` behind an SB3 logger's TensorBoard output (None without one)."""
    from stable_baselines3.common.logger import TensorBoardOutputFormat

    for fmt in logger.output_formats:
        if isinstance(fmt, TensorBoardOutputFormat):
            return fmt.writer
    return None


def gif_bytes(frames: Sequence[np.ndarray], fps: float) -> bytes:
    """Frames (H, W, 3) uint8 as an animated GIF."""
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return buf.getvalue()


def add_gif(writer, tag: str, gif: bytes, shape: tuple[int, int], step: int) -> None:
    """An animated GIF as a TensorBoard image summary (TensorBoard plays it in the Images tab). Written by hand
    because ``SummaryWriter.add_video`` needs moviepy and ffmpeg, which this project does not otherwise need."""
    from tensorboard.compat.proto.summary_pb2 import Summary

    image = Summary.Image(height=shape[0], width=shape[1], colorspace=3, encoded_image_string=gif)
    writer.file_writer.add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)
    writer.flush()


# What PeriodicEval.video writes in the run's videos/: step_<decisions>.gif, through a temporary
# .step_<n>.gif.<pid>.tmp (av_gym.atomic.temporary_name) that a kill -9 mid-write leaves behind.
VIDEO_NAME = re.compile(r"(\.)?step_(\d+)\.gif(?(1)\.\d+\.tmp)")


def remove_videos_after(folder: Path, last_step: int) -> list[Path]:
    """A resumed run's ``videos/``: remove the GIFs of the interrupted run's evaluations after its checkpoint
    (``step_<n>.gif`` with ``n > last_step``, decisions, and their write leftovers), whose model is gone and whose
    steps the resumed run evaluates again, as ``eval.csv`` keeps rows at steps <= ``last_step`` and TensorBoard's
    events from ``last_step + 1`` are cut (train.tb_events). Nothing else in the folder is touched (a user's file,
    a sub-folder, a GIF of a step at or before the checkpoint). Returns what was removed."""
    removed = []
    for path in sorted(folder.iterdir()) if folder.is_dir() else []:
        match = VIDEO_NAME.fullmatch(path.name)
        if match and int(match.group(2)) > last_step and path.is_file() and not path.is_symlink():
            path.unlink()
            removed.append(path)
    return removed


def best_json(record: dict) -> str:
    """``best.json``'s text: strict JSON, a metric without a value (NaN: no TTC in an episode set, no exit time) or an
    unbounded one (inf) is ``null``; Python's json module would write bare ``NaN`` / ``Infinity``, which other JSON
    readers (jq, JavaScript, most languages' parsers) refuse."""
    clean = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in record.items()}
    return json.dumps(clean, indent=1, allow_nan=False)


def read_best_score(path: Path) -> float:
    """The score of the best evaluation so far from ``best.json`` (``-inf`` without one, or where it is ``null``:
    any score beats it); also a file written before ``null`` (bare ``NaN``, which Python's json reads)."""
    if not path.is_file():
        return -np.inf
    value = json.loads(path.read_text())["score"]
    return -np.inf if value is None or not math.isfinite(float(value)) else float(value)


class PeriodicEval(BaseCallback):
    """SB3 ``EvalCallback`` for our metrics: at rollout starts, at least ``every`` decisions apart, and at the end of
    training, runs the deterministic policy on the fixed ``seeds`` (disjoint from training) and

    - logs ``eval/<metric>`` (collision, success, interventions, ... from ground truth) and ``eval/score``;
    - keeps ``best.zip`` (atomic) when :func:`score` improves, with ``best.json`` (score, step) beside it;
    - appends a row to ``eval.csv`` (``steps``: SB3's ``num_timesteps``, i.e. agent decisions, which are env steps
      unless ``agent.action_repeat`` > 1; wall-clock seconds since the run started; metrics): the data for "steps
      and time to reach 90 % success";
    - every ``video_every`` decisions renders the first seed's episode into ``videos/step_<n>.gif`` and TensorBoard.

    ``make_env(render_mode)`` builds the evaluation stack (the training one: same sensors and shield). ``play``, if
    given, plays the episodes instead (``play(policy, seeds) -> rows``: the batched engine, where a
    few hundred validation episodes cost seconds); videos still come from ``make_env``.

    Evaluating at a rollout's *start* (not its end, as before) means each row describes the model after every update
    of the steps it counts, and the last row, at the end of training, is ``model.zip`` itself.

    TensorBoard's ``eval/*`` equal ``eval.csv`` row for row: each evaluation writes its scalars at its own step
    (:func:`dump_prefix`; recorded without a dump they appeared one rollout late, and the final one never), and a
    resumed run drops the rows of evaluations after its checkpoint from ``eval.csv``, and their GIFs from
    ``videos/`` (:func:`remove_videos_after`), as their TensorBoard events are cut (train.tb_events)."""

    def __init__(self, make_env: Callable[[str | None], gym.Env], scenario: str, seeds: Sequence[int], every: int,
                 ckpt_dir: Path, run_dir: Path, video_every: int = 0, wall_offset: float = 0.0,
                 play: Callable[[object, list[int]], list[dict]] | None = None) -> None:
        super().__init__()
        self.make_env, self.scenario, self.seeds = make_env, scenario, [int(s) for s in seeds]
        self.play = play
        self.every, self.video_every = int(every), int(video_every)
        self.ckpt_dir, self.run_dir = Path(ckpt_dir), Path(run_dir)
        self.t0 = time.time() - wall_offset
        self._env = None
        self._last_eval = self._last_video = 0
        self.best = read_best_score(self.ckpt_dir / "best.json")

    def _on_training_start(self) -> None:
        self._last_eval = self._last_video = self.num_timesteps
        if self.num_timesteps > 0:  # a resume: evaluations after the checkpoint are of a model that is gone
            self._trim_csv(self.num_timesteps)
            removed = remove_videos_after(self.run_dir / "videos", self.num_timesteps)
            if removed:
                print(f"[train] resumed at {self.num_timesteps} decisions: removed {len(removed)} videos of the "
                      f"interrupted run's evaluations after it (videos/step_<n>.gif, n > {self.num_timesteps})")
            # the schedule goes on from the evaluations the run really made, as the uninterrupted run's does: a
            # run stopped at its last boundary before its final evaluation (a signal during the last update) gets
            # that evaluation from _on_training_end, and one that made it does not make it twice
            self._last_eval = self._last_step(self.num_timesteps)
            self._last_video = max(self._video_steps(), default=self.num_timesteps)
        if self.every > 0 and self.num_timesteps == 0:  # the starting point (e.g. a cloned policy) on the curve
            self.evaluate()

    def _on_step(self) -> bool:
        return True

    def _trim_csv(self, last_step: int) -> None:
        """Keep the ``eval.csv`` rows at steps <= ``last_step`` (TensorBoard purges the later ones on resume)."""
        from train.checkpoint import write_text_atomic

        path = self.run_dir / "eval.csv"
        if not path.is_file():
            return
        lines = path.read_text().splitlines(keepends=True)
        kept = lines[:1] + [ln for ln in lines[1:] if int(float(ln.split(",", 1)[0])) <= last_step]
        if len(kept) != len(lines):
            write_text_atomic(path, "".join(kept))

    def _last_step(self, default: int) -> int:
        """The step (decisions) of ``eval.csv``'s last row; ``default`` without one."""
        path = self.run_dir / "eval.csv"
        lines = path.read_text().splitlines()[1:] if path.is_file() else []
        return int(float(lines[-1].split(",", 1)[0])) if lines else default

    def _video_steps(self) -> list[int]:
        """The steps (decisions) of the GIFs in ``videos/`` (whole files, not a killed write's leftovers)."""
        folder = self.run_dir / "videos"
        found = (VIDEO_NAME.fullmatch(p.name) for p in (folder.iterdir() if folder.is_dir() else []))
        return [int(m.group(2)) for m in found if m and not m.group(1)]

    def _on_rollout_start(self) -> None:
        if self.every > 0 and self.num_timesteps - self._last_eval >= self.every:
            self.evaluate()

    def _on_training_end(self) -> None:
        if self.every > 0 and self.num_timesteps > self._last_eval:
            self.evaluate()

    def evaluate(self) -> dict:
        from agents.ppo import SB3Policy
        from av_gym.metrics import aggregate
        from eval.runner import run_episodes
        from train.checkpoint import save_model_atomic, write_text_atomic

        self._last_eval = step = self.num_timesteps
        if self.play is not None:
            rows = self.play(SB3Policy(self.model), self.seeds)
        else:
            if self._env is None:
                self._env = self.make_env(None)
            rows = run_episodes(self._env, SB3Policy(self.model), self.seeds, "eval", progress=False)
        means = {k: v for k, v in aggregate(rows, group_key="agent")[0].items()
                 if k in LOGGED[self.scenario] or k in ("lap_completed", "cte_mean_abs_m")}
        means["score"] = score(self.scenario, means)
        for key, value in means.items():
            if value == value:
                self.logger.record(f"eval/{key}", value)
        wall = time.time() - self.t0
        self.logger.record("eval/wall_clock_s", wall)
        dump_prefix(self.logger, "eval/", step)  # now, at this evaluation's step: TensorBoard = eval.csv
        if means["score"] > self.best:
            self.best = means["score"]
            save_model_atomic(self.model, self.ckpt_dir / "best.zip")
            write_text_atomic(self.ckpt_dir / "best.json", best_json({"score": self.best, "steps": step, **means}))
        if self.video_every > 0 and (step - self._last_video >= self.video_every or step == 0):
            self._last_video = step
            self.video(step)
        # last: the row says the evaluation is done (a resume does not redo it: _on_training_start), so what it
        # decides (best.zip, the video) is on disk first; a signal before the row makes the resume redo it all
        new_file = not (self.run_dir / "eval.csv").is_file()
        with open(self.run_dir / "eval.csv", "a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=["steps", "wall_clock_s", *means])
            if new_file:
                writer.writeheader()
            writer.writerow({"steps": step, "wall_clock_s": round(wall, 1), **means})
        return means

    def video(self, step: int) -> Path:
        """Render the first evaluation seed's episode: a GIF file and a TensorBoard image (animated)."""
        from agents.ppo import SB3Policy
        from av_gym.atomic import atomic_path

        env = self.make_env("rgb_array")
        policy = SB3Policy(self.model)
        obs, _ = env.reset(seed=self.seeds[0])
        frames, done = [env.render()], False
        while not done:
            obs, _, terminated, truncated, _ = env.step(policy.act(obs))
            frames.append(env.render())
            done = terminated or truncated
        try:  # an ActionRepeat env renders one frame per decision
            repeat = env.get_wrapper_attr("repeat")
        except AttributeError:
            repeat = 1
        fps = env.unwrapped.config["policy_frequency"] / repeat
        env.close()
        frames = [f[::2, ::2] for f in frames]  # half resolution keeps the event file small
        gif = gif_bytes(frames, fps)
        path = self.run_dir / "videos" / f"step_{step:08d}.gif"
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path, "paths.runs") as tmp:  # a kill mid-write leaves no torn GIF under the final name
            tmp.write_bytes(gif)
        writer = tensorboard_writer(self.logger)
        if writer is not None:
            add_gif(writer, "eval/episode", gif, frames[0].shape[:2], step)
        return path


CUSTOM_SCALARS = {
    "left_turn": {
        "safety": {"collision rate": ["Multiline", ["episode/collision", "eval/collision"]],
                   "shield interventions per episode": ["Multiline", ["episode/interventions", "eval/interventions"]],
                   "min TTC (s)": ["Multiline", ["episode/min_ttc_s", "eval/min_ttc_s"]]},
        "progress": {"success rate": ["Multiline", ["episode/success", "eval/success"]],
                     "time to exit (s)": ["Multiline", ["episode/time_to_exit_s", "eval/time_to_exit_s"]],
                     "mean speed (m/s)": ["Multiline", ["episode/mean_speed_mps", "eval/mean_speed_mps"]]},
    },
    "lane_keeping": {
        "safety": {"lane departures": ["Multiline", ["episode/lane_departures"]],
                   "max |CTE| (m)": ["Multiline", ["episode/cte_max_abs_m", "eval/cte_max_abs_m"]]},
        "progress": {"laps completed": ["Multiline", ["episode/lap_completed", "eval/lap_completed"]],
                     "mean |CTE| (m)": ["Multiline", ["episode/cte_mean_abs_m", "eval/cte_mean_abs_m"]]},
    },
}


class HParamsCallback(BaseCallback):
    """At the start of a (non-resumed) run: the hyperparameters in TensorBoard's HParams tab, against the final
    evaluation metrics, and the custom-scalars layout that groups safety against progress curves."""

    def __init__(self, hparams: dict, scenario: str) -> None:
        super().__init__()
        self.hparams, self.scenario = hparams, scenario

    def _on_training_start(self) -> None:
        from stable_baselines3.common.logger import HParam

        metrics = {"eval/score": 0.0, **{f"eval/{k}": 0.0 for k in LOGGED[self.scenario][:2]}}
        values = {k: v if isinstance(v, (int, float, str, bool)) else str(v) for k, v in self.hparams.items()}
        self.logger.record("hparams", HParam(values, metrics), exclude=("stdout", "log", "json", "csv"))
        writer = tensorboard_writer(self.logger)
        if writer is not None:
            writer.add_custom_scalars(CUSTOM_SCALARS[self.scenario])

    def _on_step(self) -> bool:
        return True
