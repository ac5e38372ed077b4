"""The laps ``python -m eval`` drives again for its figures (``eval.plots``) act with torch on one thread, as the
evaluated episodes do (``eval.runner.single_threaded_torch``). With ``n_envs > 1`` the episodes run in worker
processes and the parent never set it: the figures' lap then ran torch's default pool (one thread per core), which
spins on a busy machine (PilotNet on the cameras: ~7 steps/s instead of ~340 on 2 shared cores) and may sum a
network's matmuls in another order than the evaluated lap did."""

from __future__ import annotations

import gymnasium as gym
import pytest

import av_gym  # noqa: F401  (registers the envs)
import eval.agents
from eval.plots import record_lap, turn_videos

torch = pytest.importorskip("torch")


class _Acted(Exception):
    """Raised by the probe at its first action: one step says what it needs, the lap need not be driven."""


class _ThreadProbe:
    """A policy that records torch's intra-op thread count when it is first asked to act, then stops the lap."""

    def __init__(self) -> None:
        self.threads: int | None = None

    def reset(self) -> None:
        pass

    def act(self, obs):
        self.threads = torch.get_num_threads()
        raise _Acted


@pytest.fixture
def two_torch_threads():
    """torch as a fresh parent process of a 2-core machine has it (restored afterwards)."""
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_the_figures_lap_acts_with_one_torch_thread(two_torch_threads):
    env = gym.make("av_gym/LaneKeepingLap-v0")
    probe = _ThreadProbe()
    try:
        with pytest.raises(_Acted):
            record_lap(env, probe, seed=0)
    finally:
        env.close()
    assert probe.threads == 1


def test_the_left_turn_video_episode_acts_with_one_torch_thread(two_torch_threads, monkeypatch, tmp_path):
    probe = _ThreadProbe()
    monkeypatch.setattr(eval.agents, "resolve_agent", lambda spec, env, env_name, checkpoints: (spec, probe))
    plan = eval.agents.plan_agent("always_proceed", "left_turn", eval.agents.compose_group("sensors", "truth"),
                                  eval.agents.compose_group("shield", "none"), "checkpoints")
    with pytest.raises(_Acted):
        turn_videos({"name": "left_turn"}, [plan], tmp_path, 0, "checkpoints")
    assert probe.threads == 1
