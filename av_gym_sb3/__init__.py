"""The torch/SB3 pieces that a saved model names by module: SB3 pickles ``policy_kwargs`` (the ego-attention
features extractor class) into every ``model.zip``, and loading it imports that module again. Here, under a name of
its own, ``PPO.load`` of a shipped reference works in any project: under the harness's ``agents`` it imported the
user's own ``agents`` package when there was one. Above the library (it imports torch and SB3, which ``av_gym``
never does), below the harness (``agents`` builds on it)."""
