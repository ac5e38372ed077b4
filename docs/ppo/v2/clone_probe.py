"""Clone a teacher onto a fresh PPO policy and evaluate the clone (deterministic) on 100 validation seeds.

    python docs/ppo/v2/clone_probe.py agent.extractor=attention agent.init_epochs=40 agent.init_lr=1e-3

Overrides are applied to `agent=ppo_turn` (docs/ppo.md, round 2, the cloning ablation)."""
import sys, time
import numpy as np
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from stable_baselines3.common.vec_env import DummyVecEnv

from agents.ppo import SB3Policy, make_ppo
from av_gym.make import make_env
from eval.runner import run_episodes
from train.ppo import _env_factory, make_teacher, pretrain_from_teacher

with initialize_config_module("conf", version_base="1.3"):
    cfg = compose("train", overrides=["agent=ppo_turn", *sys.argv[1:]])
a = cfg.agent
plain = [OmegaConf.to_container(c, resolve=True) for c in (cfg.env, cfg.sensors, cfg.shield)]
venv = DummyVecEnv([lambda: _env_factory(*plain, 0.0, 5, "go_yield", timeout_is_terminal=True)])
model = make_ppo(venv, OmegaConf.to_container(a, resolve=True), seed=0, tensorboard_log=None)
teacher = make_teacher(str(a.init), "go_yield", "left_turn", 5)
demo = _env_factory(*plain, 0.0, 5, "go_yield")
t = time.time()
stats = pretrain_from_teacher(model, demo, teacher, range(500000, 500000 + int(a.init_episodes)), float(a.gamma),
                              int(a.init_epochs), int(a.batch_size), 0.0, int(a.get("init_dagger_rounds", 0)),
                              a.get("init_lr"))
t_clone = time.time() - t
env = make_env(cfg.env, cfg.sensors, cfg.shield)
rows = run_episodes(env, SB3Policy(model, repeat=5, actions="go_yield"), range(100000, 100100), "x", progress=False)
c = np.mean([r["collision"] for r in rows]); s = np.mean([r["success"] for r in rows])
print(f"{' '.join(sys.argv[1:])}: acc {stats['accuracy']:.3f} ({stats['decisions']} dec, {t_clone:.0f} s) "
      f"-> collision {c:.2f} success {s:.2f}", flush=True)
