"""GO if PPO's P(GO) >= a threshold, instead of the argmax, on validation seeds 100000+ (docs/ppo.md).

``python docs/ppo/threshold_sweep.py AGENT SHIELD EPISODES THRESHOLDS``, e.g. ``ppo_turn aeb 100 0.5,0.35,0.2,0.1``
(SHIELD ``none`` for none). AGENT is a trained go/yield agent (its newest checkpoint, else the reference one)."""

from __future__ import annotations

import sys

import numpy as np
import torch as th

from agents.go_yield import GO, YIELD
from av_gym.make import make_env
from eval.agents import compose_group, plan_agent, resolve_agent
from eval.runner import run_episodes


class ThresholdedGo:
    """Stands in for an SB3 model inside :class:`agents.ppo.SB3Policy`: GO when P(GO) >= ``threshold``."""

    def __init__(self, model, threshold: float) -> None:
        self.model, self.threshold = model, float(threshold)

    def predict(self, obs, deterministic: bool = True):
        tensor, _ = self.model.policy.obs_to_tensor(obs)
        with th.no_grad():
            p_go = float(self.model.policy.get_distribution(tensor).distribution.probs[0, GO])
        return np.array(GO if p_go >= self.threshold else YIELD), None


def main(agent: str, shield: str, episodes: int, thresholds: list[float]) -> None:
    spec = agent if shield == "none" else f"{agent}+{shield}"
    env_cfg = compose_group("env", "left_turn")
    plan = plan_agent(spec, "left_turn", compose_group("sensors", "truth"), compose_group("shield", "none"),
                      "checkpoints")
    for threshold in thresholds:
        env = make_env(env_cfg, plan.sensors, plan.shield)
        _, policy = resolve_agent(plan.spec, env, "left_turn", "checkpoints")
        policy.model = ThresholdedGo(policy.model, threshold)
        rows = run_episodes(env, policy, range(100000, 100000 + episodes), spec, progress=False)
        mean = {k: np.mean([r.get(k, 0.0) for r in rows]) for k in ("collision", "success", "interventions")}
        print(f"{spec} P(GO) >= {threshold}: collision {mean['collision']:.3f} success {mean['success']:.3f} "
              f"interventions {mean['interventions']:.2f}", flush=True)


if __name__ == "__main__":
    if len(sys.argv) != 5:
        sys.exit("usage: python docs/ppo/threshold_sweep.py AGENT SHIELD|none EPISODES T1,T2,... "
                 "(e.g. ppo_turn aeb 100 0.5,0.35,0.2,0.1)")
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), [float(x) for x in sys.argv[4].split(",")])
