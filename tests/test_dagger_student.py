"""DAgger's student (train/dagger.py ``LabelJob.student``, ``student_model``): a whole SB3 PPO, as
:func:`agents.ppo.make_ppo` builds it, so that ``learn`` on it collects ``n_steps`` x ``n_envs`` steps (a 2-step
rollout buffer, which saved ~10 kB resident, made ``learn`` on the object collect the wrong number of steps)."""

from __future__ import annotations

import pytest
import torch

from agents.dagger import DaggerParams
from agents.ppo import make_ppo
from conf.presets import compose_group
from train.dagger import LabelJob


@pytest.mark.slow  # ~4.5 s at load 4: the batch, SB3's first model and one rollout with its update
def test_the_student_is_make_ppos_model_and_learn_collects_n_steps_per_row():
    agent = {**DaggerParams().as_dict(), "actions": "go_yield", "action_repeat": 5, "extractor": "mlp",
             "net_arch": [8], "n_steps": 8, "batch_size": 8, "n_epochs": 1}
    job = LabelJob({"name": "left_turn"}, compose_group("sensors", "turn_truth"), {"name": "none", "kind": "none"},
                   agent, 3, "batched", 1)
    venv = job.batch(2)
    try:
        reference = make_ppo(venv, agent, seed=3, tensorboard_log=None, device="cpu")
        student = job.student(venv)  # what the DAgger parent and every labelling process build
        for (name, a), (_, b) in zip(reference.policy.state_dict().items(), student.policy.state_dict().items()):
            assert torch.equal(a, b), name
        assert student.rollout_buffer.buffer_size == student.n_steps == 8
        before = [p.detach().clone() for p in student.policy.parameters()]
        student.learn(total_timesteps=16)  # one rollout: 8 steps x 2 rows, then one epoch of updates
        assert student.num_timesteps == 16 and student.rollout_buffer.full
        assert any(not torch.equal(a, b) for a, b in zip(before, student.policy.parameters()))
    finally:
        venv.close()
