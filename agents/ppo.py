"""PPO from stable-baselines3 as an agent kind: its parameters (:class:`PPOParams`, every field of
``agent=ppo``), a factory from them, and a :class:`Policy` around a trained model. SB3 is imported only when a model
is made or loaded, so the config checker and Hydra's defaults (``agent_kind/ppo``) do not pay for it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from agents.registry import TEACHERS, AgentKind, AgentParams
from av_gym.errors import ConfigError
from av_gym.params import param
from av_gym.wrappers import ACTION_SET_NAMES, ACTION_SETS, action_set, flat_space, flatten_obs

if TYPE_CHECKING:
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecEnv

# Env stacks outside the batched engine (per-env sensors, a process each with subproc, ~180 MB apiece): 64 already
# oversubscribes any workstation's cores.
PROCESSES_MAX = 64
PPO_KEYS = ("learning_rate", "n_steps", "batch_size", "n_epochs", "gamma", "gae_lambda", "clip_range", "ent_coef",
            "vf_coef", "max_grad_norm", "target_kl")
__all__ = ["PPOAgent", "PPOParams", "SB3Policy", "flat_space", "flatten_obs", "make_ppo", "sb3_space"]


@dataclass(frozen=True)
class PPOParams(AgentParams):
    """PPO (stable-baselines3) and its training setup. Defaults: conf/agent/ppo.yaml's, a budget sized so that the
    default ``python -m train agent=ppo`` finishes in < 5 min on 2 CPU cores."""

    kind: Literal["ppo"] = param("ppo")
    name: str = param("ppo")
    policy: Literal["MultiInputPolicy"] = param("MultiInputPolicy", doc="the envs observe a Dict")
    total_timesteps: int = param(24000, "policy steps", ge=1, doc="summed over n_envs (x action_repeat env steps)")
    n_envs: int = param(2, ge=1, le=4096, doc="training envs, one per core (batched: rows of one numpy batch, "
                                                "<= 4096, ~16x ppo_turn's 64; more asked for GiBs)")
    vec_env: Literal["subproc", "dummy", "batched"] = param(
        "subproc", doc="subproc: one process per env | dummy: in-process | batched: the left turn's numpy batch "
                       "(av_gym/batched/vec_env.py)")
    learning_rate: float = param(3.0e-4, gt=0, doc="Adam step (SB3's default)")
    n_steps: int = param(512, "policy steps", ge=2, doc="per env per rollout: 1024 steps per update with 2 envs")
    batch_size: int = param(128, ge=2, doc="minibatch size")
    n_epochs: int = param(10, ge=1, doc="passes over each rollout")
    gamma: float = param(0.99, ge=0, le=1, doc="discount: at 10 Hz a 10 s effective horizon, about one left-turn "
                                               "episode")
    gae_lambda: float = param(0.95, ge=0, le=1, doc="GAE lambda (SB3's default)")
    clip_range: float = param(0.2, gt=0, doc="PPO clip (SB3's default)")
    ent_coef: float = param(0.01, ge=0, doc="entropy bonus: keeps exploring the slow-down actions early on")
    vf_coef: float = param(0.5, ge=0, doc="value loss weight (SB3's default)")
    max_grad_norm: float = param(0.5, gt=0, doc="gradient clip (SB3's default)")
    target_kl: float | None = param(None, gt=0, doc="SB3 ends an update's epochs once the KL passes 1.5x this; "
                                                    "null: no limit")
    net_arch: tuple[int, ...] = param((128, 128), ge=1, doc="hidden sizes of the policy and value heads")
    extractor: Literal["mlp", "attention"] = param(
        "mlp", doc="mlp: SB3 concatenates the inputs | attention: ego-attention over the left turn's road users "
                   "(agents/attention.py, Leurent & Mercat 2019), needs obs['turn']")
    attention_dim: int = param(64, ge=1, doc="width of each entity's embedding (attention only; the paper's 64)")
    attention_heads: int = param(2, ge=1, doc="attention heads (attention only; the paper's 2)")
    log_std_init: float | None = param(None, doc="continuous actions: initial log std of the Gaussian; null: SB3's "
                                                 "0 (std 1)")
    cnn_output_dim: int | None = param(None, ge=1, doc="image inputs: width of the NatureCNN's output layer; null: "
                                                       "SB3's 256")
    device: Literal["cpu", "cuda", "auto"] = param("cpu", doc="torch device")
    actions: Literal[ACTION_SET_NAMES] = param(
        "env", doc=" | ".join(f"{name}: {a.doc}" for name, a in ACTION_SETS.items()))
    action_repeat: int = param(1, "env steps", ge=1, doc="env steps each decision is held for "
                                                         "(av_gym/wrappers.py ActionRepeat)")
    intervention_cost: float = param(0.0, "reward/s", ge=0, doc="reward per second of shield override "
                                                                "(av_gym/wrappers.py InterventionCost)")
    timeout_is_terminal: bool = param(False, doc="the time limit ends an episode as a failure, not bootstrapped "
                                                 "(av_gym/wrappers.py TimeLimitIsTerminal)")
    init: str | None = param(None, doc="behaviour-clone this agent (conf/agent/<init>.yaml, a kind in "
                                       "agents/registry.py TEACHERS) before PPO; null: from scratch")
    init_episodes: int = param(150, "episodes", ge=1, doc="teacher episodes (seeds 500000+), DAgger rounds "
                                                          "included")
    init_epochs: int = param(40, ge=1, doc="epochs of behaviour cloning")
    init_action_noise: float = param(0.0, ge=0, doc="DART: std of the perturbation of the executed action "
                                                    "(continuous actions; the label stays clean)")
    init_lr: float | None = param(None, gt=0, doc="Adam step while cloning; null: learning_rate")
    init_dagger_rounds: int = param(0, ge=0, doc="DAgger rounds after the teacher's episodes (Ross et al. 2011)")
    init_from: str | None = param(None, doc="start from this checkpoint's network instead (a run or reference "
                                            "folder, or its model.zip; same observation and action spaces): PPO "
                                            "fine-tuning of a DAgger student or an earlier run; null: fresh")

    def relations(self) -> list[str]:
        found = super().relations()
        if self.vec_env != "batched" and self.n_envs > PROCESSES_MAX:
            found.append(f"@n_envs must be at most {PROCESSES_MAX} with @vec_env={self.vec_env} (one env stack, and "
                         f"with subproc one process, each), got {self.n_envs}; vec_env=batched takes more")
        if self.init_from is not None:
            if not Path(self.init_from).exists():
                found.append(f"@init_from must be a checkpoint folder or model.zip, got {self.init_from!r}: no such "
                             f"file or folder")
            if self.init is not None:
                found.append(f"@init_from and @init both set ({self.init_from!r}, {self.init!r}): start from a "
                             f"checkpoint or clone a teacher, not both (@init=null starts from the checkpoint)")
        if self.init is not None:
            allowed = teacher_agents()
            if self.init not in allowed:
                found.append(f"@init must be one of {[*allowed, None]}, got {self.init!r}")
            elif self.init_episodes < 1 + self.init_dagger_rounds:
                found.append(f"@init_episodes must be at least 1 + @init_dagger_rounds = {1 + self.init_dagger_rounds} "
                             f"(the teacher and each DAgger round drive their own episodes), got {self.init_episodes}")
        return found


def teacher_agents() -> list[str]:
    """The agent configs (``conf/agent/<name>.yaml``) ``agent.init`` may name: those of a kind in TEACHERS."""
    from agents.configs import agent_kind_of, available_agents

    return [name for name in available_agents() if agent_kind_of(name) in TEACHERS]


def sb3_space(space: gym.Space) -> gym.Space:
    """The observation space an SB3 model trained on ``space`` reports: flattened, images channel-first (SB3
    wraps image envs in ``VecTransposeImage``). Used to check that a checkpoint fits an env."""
    from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
    from stable_baselines3.common.vec_env import VecTransposeImage

    space = flat_space(space)
    if not isinstance(space, spaces.Dict):
        return space
    return spaces.Dict({k: VecTransposeImage.transpose_space(v, k) if is_image_space(v)
                        and not is_image_space_channels_first(v) else v for k, v in space.spaces.items()})


def make_ppo(env: VecEnv, hyper: dict[str, Any], *, seed: int, tensorboard_log: str | None,
             device: str = "cpu") -> "PPO":
    """A fresh SB3 PPO on ``env``. ``hyper`` holds ``policy``, ``net_arch`` (hidden sizes), optionally
    ``log_std_init`` (continuous actions: initial log std of the Gaussian), ``cnn_output_dim`` (image inputs: width of
    the NatureCNN's output layer, SB3's default 256), ``extractor`` (``mlp``: SB3's concatenation of the inputs;
    ``attention``: :class:`agents.attention.EgoAttention` over the left turn's road users, ``attention_dim`` wide
    with ``attention_heads`` heads) and :data:`PPO_KEYS`."""
    from stable_baselines3 import PPO

    kwargs = {k: hyper[k] for k in PPO_KEYS if k in hyper}
    policy_kwargs = {"net_arch": list(hyper["net_arch"])} if hyper.get("net_arch") else {}
    if hyper.get("log_std_init") is not None:
        policy_kwargs["log_std_init"] = float(hyper["log_std_init"])
    if hyper.get("cnn_output_dim") is not None:
        # MultiInputPolicy's CombinedExtractor names the CNN's width cnn_output_dim; CnnPolicy's NatureCNN features_dim
        key = "features_dim" if hyper.get("policy") == "CnnPolicy" else "cnn_output_dim"
        policy_kwargs["features_extractor_kwargs"] = {key: int(hyper["cnn_output_dim"])}
    if hyper.get("extractor", "mlp") == "attention":  # the left turn's road users through ego-attention
        from av_gym_sb3.attention import EgoAttention

        policy_kwargs["features_extractor_class"] = EgoAttention
        policy_kwargs["features_extractor_kwargs"] = {"embed_dim": int(hyper.get("attention_dim", 64)),
                                                      "heads": int(hyper.get("attention_heads", 2))}
    return PPO(hyper.get("policy", "MultiInputPolicy"), env, seed=seed, tensorboard_log=tensorboard_log,
               policy_kwargs=policy_kwargs or None, device=device, verbose=0, **kwargs)


class SB3Policy:
    """Deterministic action of a trained SB3 model for one observation. With ``repeat`` > 1 (a model trained with
    :class:`av_gym.wrappers.ActionRepeat`) the model is asked every ``repeat`` calls and its action held in between."""

    def __init__(self, model: Any, repeat: int = 1, actions: str = "env") -> None:
        self.model, self.repeat, self.actions = model, int(repeat), actions
        self._k, self._action = 0, None

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> "SB3Policy":
        # SB3 zips contain pickled objects: only paths the user gave (or our own checkpoints/ folder) get here.
        from stable_baselines3 import PPO

        return cls(PPO.load(str(path), device=device))

    def reset(self) -> None:
        self._k, self._action = 0, None

    def act(self, obs: Any) -> Any:
        if self._k % self.repeat == 0:
            action, _ = self.model.predict(flatten_obs(obs), deterministic=True)
            self._action = int(action) if np.ndim(action) == 0 else action
        self._k += 1
        # the held choice becomes the env's action at every env step, as in training (go_yield: a meta-action)
        return action_set(self.actions).act_one(self._action, obs)


class PPOAgent(AgentKind):
    """Trained by :func:`train.ppo.train_ppo`; ``model.zip`` is an SB3 zip (a pickle: load only what you trust)."""

    Params = PPOParams
    checkpoint = "model.zip"

    @classmethod
    def load(cls, model_path: Path, env: gym.Env) -> SB3Policy:
        from agents.checkpoint import check_sb3_zip, describe_space, saved_config, unloadable

        check_sb3_zip(model_path)  # again: the file may have changed since the command-line check
        try:
            policy = SB3Policy.load(model_path)
        except Exception as exc:  # noqa: BLE001 - a zip of the right shape that SB3 still cannot unpickle
            raise unloadable(model_path, exc) from None
        saved = saved_config(model_path)
        trained = saved.get("agent", {})
        if policy.model.observation_space != sb3_space(env.observation_space):
            config = Path(model_path).parent / "config.yaml"
            how = ("same sensors preset and env settings as in its training, see its config.yaml" if saved else
                   f"it has no {config.name} beside it saying which sensors preset and env settings it was trained "
                   f"with: copy its run's config.yaml to {config}, or give them on the command line")
            raise ConfigError(f"checkpoint {str(model_path)!r} expects observations "
                              f"{describe_space(policy.model.observation_space)}, this env gives "
                              f"{describe_space(sb3_space(env.observation_space))} ({how})")
        # A policy's actions become the env's by its action set (av_gym/wrappers.py): it needs that env space.
        needs = action_set(trained.get("actions") or "env").env_space(policy.model.action_space)
        if needs != env.action_space:
            raise ConfigError(f"checkpoint {str(model_path)!r} acts in {needs}, this env expects "
                              f"{env.action_space} (env.action must be as in its training)")
        policy.repeat = int(trained.get("action_repeat", 1) or 1)  # decides every `repeat` env steps, as in training
        policy.actions = trained.get("actions") or "env"  # go_yield: its two choices mapped to meta-actions
        return policy
