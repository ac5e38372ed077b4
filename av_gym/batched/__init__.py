"""The left turn for B environments at once, as numpy arrays: :mod:`av_gym.batched.left_turn` (the
episodes, reward, truth and observations) and :mod:`av_gym.batched.vec_env` (SB3 ``VecEnv`` / Gymnasium
``VectorEnv``). It sits above ``envs``/``sensors``/``estimation`` and ``make`` (it reuses their models and
config), and nothing in those layers imports it (tests/test_imports.py)."""
