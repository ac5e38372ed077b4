"""A recurrent GO/YIELD student: the DAgger students' per-decision features and road-user encoder, a GRU over the
episode's decisions on top. CleanRL-style: the whole model, its driver and its checkpoint here.

Why a GRU: the feed-forward students see one decision's observation; the planner they imitate keeps a belief per
driver over every indicator reading so far (agents/belief.py), of which ``turn_truth_memory`` hands them a
summary (P(right, straight, left) per object). Whether the history holds more about the label than that summary
is a measurement, not an argument: this student reads the whole history, and train/dagger_recurrent.py fits it
on a DAgger run's aggregate (whose states are stored episode by episode, in decision order).

The network, per decision t of an episode: ``e_t = EgoAttention(obs_t)`` (av_gym_sb3/attention.py, the same
encoder as the feed-forward students), ``h_t = GRU(e_t, h_{t-1})`` with ``h_0 = 0`` at the episode's first
decision, and ``logits_t = MLP([e_t, h_t])`` over (YIELD, GO): the head sees the present decision's features
directly, so memory is an addition to the feed-forward form, not a bottleneck in front of it. ``hidden=0`` drops
the GRU (the same head on ``e_t`` alone): the feed-forward control of the same code and fit.

Driving: :class:`RecurrentPolicy` keeps one hidden state, one decision counter and one held choice per row; a row's
are reset when its episode starts (``reset_rows``: the batched evaluation's restarts; ``reset``: the per-env
:class:`agents.base.Policy`'s). As the go/yield students, it decides every ``action_repeat`` env steps (GO where
its P(GO) >= ``go_threshold``) and its held choice becomes the env's meta-action at every step
(:func:`av_gym.wrappers.action_set`). Checkpoints (:func:`save_student`, :func:`load_student`): one torch file
written atomically, holding the form (every size, the observation it reads, the actions) and the weights, loaded
with ``weights_only`` (no pickle of code).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from torch import nn

from av_gym.errors import ConfigError
from av_gym.wrappers import GO, YIELD, action_set
from av_gym_sb3.attention import EgoAttention

FORMAT = "av_gym.recurrent_student/1"
CHECKPOINT_FIELD = "paths.checkpoints"


@dataclass(frozen=True)
class RecurrentForm:
    """Everything that builds a :class:`RecurrentStudent` and drives it (saved in its checkpoint)."""

    turn_dim: int  # obs["turn"] columns (5 + 12 N, av_gym/estimation/turn_features.py)
    intent_shape: tuple[int, ...] | None = None  # obs["intent"] (N, k), None without it
    attention_dim: int = 64  # the encoder's width (agent.attention_dim of the feed-forward students)
    attention_heads: int = 2
    hidden: int = 64  # the GRU's state; 0: no GRU (the feed-forward control)
    net_arch: tuple[int, ...] = (128, 128)  # the head's hidden layers
    actions: str = "go_yield"
    action_repeat: int = 5  # env steps per decision
    go_threshold: float = 0.5  # GO where P(GO) >= this

    def observation_space(self) -> gym.spaces.Dict:
        """The observation the encoder reads (the bounds are not used by the network)."""
        keys = {"turn": gym.spaces.Box(-np.inf, np.inf, (self.turn_dim,), np.float32)}
        if self.intent_shape is not None:
            keys["intent"] = gym.spaces.Box(0.0, 1.0, tuple(self.intent_shape), np.float32)
        return gym.spaces.Dict(keys)

    @classmethod
    def of_observations(cls, obs: dict[str, np.ndarray], **sizes: Any) -> "RecurrentForm":
        """The form reading observations shaped as ``obs`` (arrays with one leading row axis), with ``sizes``."""
        if "turn" not in obs:
            raise ConfigError(f"a recurrent student reads obs['turn'] (sensors=turn_truth*), got keys {sorted(obs)}")
        intent = tuple(int(n) for n in np.shape(obs["intent"])[1:]) if "intent" in obs else None
        return cls(turn_dim=int(np.shape(obs["turn"])[1]), intent_shape=intent, **sizes)


def _head(n_in: int, arch: tuple[int, ...]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in arch:
        layers += [nn.Linear(n_in, width), nn.ReLU()]
        n_in = width
    return nn.Sequential(*layers, nn.Linear(n_in, 2))


class RecurrentStudent(nn.Module):
    """Logits over (YIELD, GO) per decision from the episode's decisions so far (module docstring)."""

    def __init__(self, form: RecurrentForm) -> None:
        super().__init__()
        self.form = form
        self.encoder = EgoAttention(form.observation_space(), form.attention_dim, form.attention_heads)
        self.gru = nn.GRU(form.attention_dim, form.hidden, batch_first=True) if form.hidden > 0 else None
        self.head = _head(form.attention_dim + form.hidden, tuple(form.net_arch))

    def initial_state(self, n: int) -> th.Tensor:
        """The hidden state (n, hidden) at an episode's first decision: zeros."""
        return th.zeros(n, self.form.hidden)

    def forward(self, obs: dict[str, th.Tensor], valid: th.Tensor | None = None) -> th.Tensor:
        """Logits (B, T, 2) for B episodes of T decisions from their starts (``obs[key]``: (B, T, ...));
        ``valid`` (B, T): the decisions that exist (an episode's padding after its end is not encoded; the GRU is
        causal, so padding never reaches an earlier decision)."""
        b, t = obs["turn"].shape[:2]
        flat = {k: v.reshape(b * t, *v.shape[2:]) for k, v in obs.items()}
        keep = th.ones(b * t, dtype=th.bool) if valid is None else valid.reshape(b * t)
        e = th.zeros(b * t, self.form.attention_dim, dtype=flat["turn"].dtype)
        e[keep] = self.encoder({k: v[keep] for k, v in flat.items()})
        e = e.reshape(b, t, -1)
        if self.gru is None:
            return self.head(e)
        h, _ = self.gru(e)
        return self.head(th.cat([e, h], dim=-1))

    def step(self, obs: dict[str, th.Tensor], h: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """One decision for n rows: logits (n, 2) and the next hidden state (n, hidden) from ``h``."""
        e = self.encoder(obs)
        if self.gru is None:
            return self.head(e), h
        out, h_next = self.gru(e[:, None], h[None].contiguous())
        return self.head(th.cat([e, out[:, 0]], dim=-1)), h_next[0]


class RecurrentPolicy:
    """A :class:`RecurrentStudent` driving ``n_rows`` episodes at once (the batched evaluation: one hidden state
    per row) or one (:class:`agents.base.Policy`: ``reset`` and ``act`` on unbatched observations)."""

    def __init__(self, student: RecurrentStudent, n_rows: int = 1) -> None:
        self.student = student.eval()
        self.form = student.form
        self.actions, self.repeat = self.form.actions, int(self.form.action_repeat)
        self.start_rows(n_rows)

    def start_rows(self, n_rows: int) -> None:
        """Room for ``n_rows`` episodes, every row at its episode's start."""
        self.h = self.student.initial_state(n_rows)
        self.k = np.zeros(n_rows, dtype=np.int64)  # env steps since the row's episode started
        self.held = np.full(n_rows, YIELD, dtype=np.int64)  # the row's choice until its next decision

    def reset_rows(self, rows: np.ndarray) -> None:
        """The episodes of ``rows`` start anew: no memory of the episode the row drove before."""
        rows = np.asarray(rows, dtype=np.int64)
        self.h[th.as_tensor(rows)] = 0.0
        self.k[rows], self.held[rows] = 0, YIELD

    def decide(self, obs: dict[str, np.ndarray], rows: np.ndarray) -> None:
        """The rows ``rows`` (``obs[key][i]`` is row ``rows[i]``'s) at a decision: their hidden states step and
        their choices become GO where P(GO) >= go_threshold."""
        x = {k: th.as_tensor(np.asarray(v), dtype=th.float32) for k, v in obs.items()}
        idx = th.as_tensor(rows)
        with th.no_grad():
            logits, self.h[idx] = self.student.step(x, self.h[idx])
            p_go = th.softmax(logits, dim=-1)[:, GO].numpy()
        self.held[rows] = np.where(p_go >= self.form.go_threshold, GO, YIELD)

    def act_rows(self, obs: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
        """The env's actions for ``rows`` (``obs[key]`` holds every row); rows at a decision step decide first."""
        rows = np.asarray(rows, dtype=np.int64)
        ask = rows[self.k[rows] % self.repeat == 0]
        if len(ask):
            self.decide({k: np.asarray(obs[k])[ask] for k in self._reads(obs)}, ask)
        self.k[rows] += 1
        return action_set(self.actions).act(self.held[rows], {k: np.asarray(v)[rows] for k, v in obs.items()})

    def _reads(self, obs: dict) -> list[str]:
        return ["turn"] + (["intent"] if self.form.intent_shape is not None else [])

    def reset(self) -> None:
        self.start_rows(1)

    def act(self, obs: dict) -> int:
        return int(self.act_rows({k: np.asarray(v)[None] for k, v in obs.items()}, np.zeros(1, dtype=np.int64))[0])


def save_student(student: RecurrentStudent, path: str | Path, extra: dict | None = None) -> Path:
    """The student's form and weights (and ``extra``: plain values, e.g. its fit's record) to ``path``,
    atomically (av_gym/atomic.py)."""
    from av_gym.atomic import atomic_path

    form = asdict(student.form)
    record = {"format": FORMAT, "form": form, "state_dict": student.state_dict(), "extra": extra or {}}
    with atomic_path(path, CHECKPOINT_FIELD) as tmp:
        th.save(record, str(tmp))
    return Path(path)


def load_student(path: str | Path, **changes: Any) -> RecurrentStudent:
    """The student :func:`save_student` wrote to ``path`` (its form with ``changes``, e.g. ``go_threshold``); one
    line for a file that is not one."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path} does not exist: give a recurrent student's checkpoint (train/dagger_recurrent.py)")
    try:
        record = th.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one line
        raise ConfigError(f"{path} is not a recurrent student's checkpoint ({' '.join(str(exc).split())[:120]})") \
            from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise ConfigError(f"{path} is not a recurrent student's checkpoint (format {FORMAT!r} expected)")
    saved = dict(record["form"])
    for key in ("intent_shape", "net_arch"):
        saved[key] = tuple(saved[key]) if saved[key] is not None else None
    student = RecurrentStudent(replace(RecurrentForm(**saved), **changes))
    student.load_state_dict(record["state_dict"])
    return student.eval()


__all__ = ["RecurrentForm", "RecurrentStudent", "RecurrentPolicy", "save_student", "load_student"]
