"""Ego-attention features extractor for a variable set of road users (Leurent & Mercat, "Social Attention for
Autonomous Decision-Making in Dense Traffic", 2019), as an SB3 ``BaseFeaturesExtractor`` on the left turn's
``obs["turn"]`` (+ ``obs["intent"]`` where the sensors preset gives it).

Why: an MLP on the flat turn features sees object *slots* sorted by distance; the same car changes slot whenever
another comes nearer, and the rule a driver uses ("yield while *any* car will cross my path soon") must be learnt
once per slot. Ego-attention encodes every road user with one shared network and lets the ego's query pick the
ones that matter, so the policy is invariant to the order of the objects and to how many there are.

The network, as in the paper (its Fig. 2): each entity (the ego and each present object) is encoded by a shared
MLP per entity type; the ego's embedding forms the query of each head, every entity's embedding its key and
value; the heads' attention-weighted values are concatenated, projected, and added to the ego's embedding. Absent
objects (``present`` = 0) are masked out; the ego always attends at least to itself.
"""

from __future__ import annotations

import gymnasium as gym
import torch as th
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from av_gym.estimation.turn_features import EGO_FEATURES, OBJECT_FEATURES


def _mlp(n_in: int, width: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU())


class EgoAttention(BaseFeaturesExtractor):
    """``features_dim`` = ``embed_dim``. Observation: a ``Dict`` with ``turn`` (``5 + 12·N``,) and optionally
    ``intent`` (``(N, k)``), as :class:`av_gym.estimation.turn_features.TurnFeatures` / ``TurnIntent`` give them."""

    def __init__(self, observation_space: gym.spaces.Dict, embed_dim: int = 64, heads: int = 2) -> None:
        super().__init__(observation_space, features_dim=embed_dim)
        if "turn" not in observation_space.spaces:
            raise ValueError("agent.extractor=attention needs obs['turn'] (sensors=turn_truth or turn_perceived)")
        if embed_dim % heads:
            raise ValueError(f"agent.attention_dim ({embed_dim}) must be a multiple of agent.attention_heads ({heads})")
        self.n_ego, self.n_obj_feat = len(EGO_FEATURES), len(OBJECT_FEATURES)
        self.n_objects = (observation_space["turn"].shape[0] - self.n_ego) // self.n_obj_feat
        intent = observation_space.spaces.get("intent")
        self.n_intent = int(intent.shape[-1]) if intent is not None else 0
        self.heads, self.d = heads, embed_dim // heads
        self.ego_encoder = _mlp(self.n_ego, embed_dim)
        self.object_encoder = _mlp(self.n_obj_feat + self.n_intent, embed_dim)
        self.query = nn.Linear(embed_dim, embed_dim, bias=False)
        self.key = nn.Linear(embed_dim, embed_dim, bias=False)
        self.value = nn.Linear(embed_dim, embed_dim, bias=False)
        self.project = nn.Linear(embed_dim, embed_dim)

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        turn = observations["turn"]
        b = turn.shape[0]
        ego = turn[:, : self.n_ego]
        objects = turn[:, self.n_ego: self.n_ego + self.n_objects * self.n_obj_feat].reshape(b, self.n_objects, -1)
        present = objects[..., OBJECT_FEATURES.index("present")] > 0.5  # (B, N)
        if self.n_intent:
            objects = th.cat([objects, observations["intent"].reshape(b, self.n_objects, -1)], dim=-1)
        e_ego = self.ego_encoder(ego)  # (B, E)
        entities = th.cat([e_ego[:, None], self.object_encoder(objects)], dim=1)  # (B, 1+N, E)
        mask = th.cat([th.ones(b, 1, dtype=th.bool, device=turn.device), present], dim=1)  # (B, 1+N)

        def split(x: th.Tensor) -> th.Tensor:  # (B, L, E) → (B, heads, L, d)
            return x.reshape(b, x.shape[1], self.heads, self.d).transpose(1, 2)

        q = split(self.query(e_ego)[:, None])  # (B, H, 1, d)
        k, v = split(self.key(entities)), split(self.value(entities))  # (B, H, 1+N, d)
        scores = (q @ k.transpose(-1, -2)) / self.d ** 0.5  # (B, H, 1, 1+N)
        scores = scores.masked_fill(~mask[:, None, None, :], float("-inf"))
        attended = (th.softmax(scores, dim=-1) @ v).transpose(1, 2).reshape(b, -1)  # (B, E)
        return e_ego + self.project(attended)
