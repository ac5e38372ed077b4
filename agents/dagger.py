"""DAgger students as an agent kind: an SB3 PPO policy network trained by on-policy imitation of a
teacher (:func:`train.dagger.train_dagger`), so its checkpoint is a PPO zip that ``python -m eval`` loads as any PPO
checkpoint and PPO can fine-tune. Its Params are PPO's (the network, the env stack) plus the DAgger rounds."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from agents.ppo import PPOAgent, PPOParams, teacher_agents
from av_gym.params import param


# Why DAgger's counts are bounded (an unbounded agent.rounds runs without end, its label set growing):
# - each round refits the student on the whole aggregate, so the work grows with the square of the rounds, and
#   DAgger's gain flattens within a few rounds (the references use 6-8, docs/dagger.md): 100 is far past any use;
# - the aggregate is held in memory and saved in latest.zip after every round (resumable): about 20 kB per episode
#   on the turn features (~40 decisions of ~470 bytes, plus Python's per-state overhead), so 100,000 episodes in
#   all (rounds x round_episodes) is ~2 GB; the references label 512-1,152.
ROUNDS_MAX = 100
AGGREGATE_EPISODES_MAX = 100_000


@dataclass(frozen=True)
class DaggerParams(PPOParams):
    """On-policy imitation (DAgger, Ross et al. 2011) of ``teacher`` by a PPO policy network (conf/agent/dagger_turn.yaml).
    PPO's own fields set the network (``extractor``, ``net_arch``), the env stack (``actions``, ``action_repeat``,
    ``vec_env``, ``n_envs``, ``timeout_is_terminal``) and the critic's discount (``gamma``); ``total_timesteps`` and
    the other PPO update fields are unused (no PPO here)."""

    kind: Literal["dagger"] = param("dagger")
    name: str = param("dagger")
    teacher: str = param("lookahead", doc="the agent config that labels the student's states (a kind in "
                                          "agents/registry.py TEACHERS)")
    rounds: int = param(8, ge=1, le=ROUNDS_MAX, doc="DAgger rounds: the teacher drives the first (the student, "
                                                    "when it starts from init_from), the student the others; the "
                                                    "student is refitted on everything labelled so far after each")
    round_episodes: int = param(128, "episodes", ge=1, le=AGGREGATE_EPISODES_MAX,
                                doc="episodes driven (and labelled) in the first round (in every round when "
                                    "round_growth is 1)")
    round_growth: float = param(1.0, ge=1.0, le=4.0, doc="each round drives this many times the episodes of the one "
                                                          "before (round k: round_episodes x round_growth^k, "
                                                          "rounded): the refits' work stays proportional to the "
                                                          "final aggregate instead of its square, and the rounds "
                                                          "fall evenly on a log scale of labels; 1: equal rounds")
    fit_epochs: int = param(8, ge=1, doc="passes over the aggregated labels after each round")
    fit_lr: float = param(1.0e-3, gt=0, doc="Adam step of the supervised fit")
    fit_batch: int = param(256, ge=2, doc="minibatch of the supervised fit")
    label_margin: float = param(0.0, "m", ge=0, doc="batched look-ahead labels: GO only where the GO future also "
                                                    "keeps this centre distance from every vehicle (a more cautious "
                                                    "operating point); 0: the oracle's own choice")
    targets: Literal["labels", "go_safe"] = param(
        "labels", doc="what P(GO) is fitted to | labels: the teacher's GO/YIELD labels | go_safe: the share of the "
                      "belief planner's K GO futures that stay collision-free (teacher of kind belief_lookahead on "
                      "vec_env=batched): its label keeps one bit of that K-sample estimate, the share keeps the "
                      "rest. The labels still drive round 0, and the fit accuracy and agreement are against them; "
                      "the student drives its rounds at go_threshold (not at its argmax)")
    disagree_weight: float = param(1.0, ge=1.0, le=100.0,
                                   doc="each refit weighs the actor's loss on the aggregated states where the "
                                       "student about to be refitted (the one that drove the round) chooses "
                                       "otherwise than the teacher's label this many times a state it gets right: "
                                       "the fit spends its capacity on the states the student still gets wrong "
                                       "(recomputed every refit; discrete actions only); 1: every state alike")
    go_threshold: float = param(0.5, gt=0, lt=1, doc="go/yield students: GO where the student's P(GO) is at least "
                                                     "this (the checkpoints and validations are at it; the fit is "
                                                     "not); 0.5 = its argmax. train/operating_point.py sweeps it")
    drive_at_threshold: bool = param(False, doc="go/yield students fitted to labels: the student drives its rounds "
                                                "at go_threshold, where it is validated and used, so the labels "
                                                "fall on the states it meets there (waiting for a gap) rather than "
                                                "on those after the GOs its argmax takes and its operating point "
                                                "does not (a student from init_from saved at its own threshold is "
                                                "moved back to its fit's 0.5 first, so round 0 too is at "
                                                "go_threshold); false: at its argmax (targets go_safe always drives "
                                                "at go_threshold)")
    labeller: Literal["auto", "batched", "replica", "per_env"] = param(
        "auto", doc="batched: the look-ahead oracle on the batched engine (agents/batched_oracle.py, needs "
                    "vec_env=batched and teacher kind lookahead) | replica: the student on the per-env stack (any "
                    "sensors, e.g. turn_perceived), the oracle on a batched replica of the same episodes (left turn, "
                    "teacher kind lookahead) | per_env: the teacher on the per-env stack, one state at a time | "
                    "auto: batched on the batch, replica on the per-env left turn with the oracle, else per_env")
    workers: int = param(1, ge=1, le=64, doc="labelling processes (vec_env=batched): each round's episode seeds in "
                                             "this many contiguous parts, each driven and labelled on its own "
                                             "batch of n_envs in a spawned process holding the round's student, "
                                             "merged back into the aggregate one process gives (a row's episode "
                                             "depends on its seed only); 1: in this process")
    train_seed: int = param(600_000, ge=0, doc="first seed of the episodes the rounds drive, in the train split "
                                               "(av_gym/seeds.py; + 50,000 x seed, folded into the split): away from "
                                               "the demonstrations (500,000+) and PPO's streams (seed + steps)")

    def round_sizes(self) -> list[int]:
        """Episodes driven in each round: ``round_episodes x round_growth^k`` rounded, at least one."""
        return [max(1, round(self.round_episodes * self.round_growth ** k)) for k in range(self.rounds)]

    def relations(self) -> list[str]:
        found = super().relations()
        total = sum(self.round_sizes())
        if total > AGGREGATE_EPISODES_MAX:
            grown = f" grown by @round_growth={self.round_growth:g} a round" if self.round_growth > 1 else ""
            found.append(f"@rounds x @round_episodes must be at most {AGGREGATE_EPISODES_MAX:,} episodes (the labelled "
                         f"states are held in memory and saved each round, ~20 kB an episode), got {self.rounds} x "
                         f"{self.round_episodes}{grown} = {total:,}")
        if self.drive_at_threshold and self.actions != "go_yield":
            found.append(f"@drive_at_threshold needs a GO/YIELD student (@actions=go_yield: a threshold on P(GO)), "
                         f"got @actions={self.actions}")
        allowed = teacher_agents()
        if self.teacher not in allowed:
            found.append(f"@teacher must be one of {allowed}, got {self.teacher!r}")
        return found


class DaggerAgent(PPOAgent):
    """Trained by :func:`train.dagger.train_dagger`; ``model.zip`` is an SB3 PPO zip, loaded as PPO's."""

    Params = DaggerParams
