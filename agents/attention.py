"""The ego-attention features extractor lives in :mod:`av_gym_sb3.attention` (a module name that saved models can
carry into any project); this name stays because models saved before that move name ``agents.attention``."""

from av_gym_sb3.attention import EgoAttention

__all__ = ["EgoAttention"]
