"""``python -m train``: build env and agent from the Hydra config, train, log, checkpoint, evaluate briefly."""
