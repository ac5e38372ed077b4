"""DAgger's student (train/dagger.py ``LabelJob.student``, ``student_model``): SB3's PPO without the rollout buffer
it never fills, the same weights and the same model.zip as :func:`agents.ppo.make_ppo` builds."""

from __future__ import annotations

import json
import zipfile

import torch

from agents.dagger import DaggerParams
from agents.ppo import make_ppo
from conf.presets import compose_group
from train.dagger import LabelJob


def _buffer_bytes(model) -> int:
    buffer = model.rollout_buffer
    return sum(v.nbytes for v in buffer.observations.values()) + buffer.actions.nbytes + buffer.values.nbytes


def test_the_student_has_no_rollout_buffer_of_n_steps_and_saves_make_ppos_model(tmp_path):
    """The student's rollout buffer holds 2 steps, not make_ppo's n_steps x n_envs observations (512 x 2 rows here;
    16.4 MB of address space at 64 rows in every DAgger process, never written), while its weights, n_steps,
    batch_size and the whole model.zip (the data, the policy, the optimizer) are make_ppo's, and PPO.load reads it
    back."""
    from stable_baselines3 import PPO

    agent = {**DaggerParams().as_dict(), "actions": "go_yield", "action_repeat": 5, "extractor": "mlp",
             "net_arch": [8]}
    job = LabelJob({"name": "left_turn"}, compose_group("sensors", "turn_truth"), {"name": "none", "kind": "none"},
                   agent, 3, "batched", 1)
    venv = job.batch(2)
    try:
        reference = make_ppo(venv, agent, seed=3, tensorboard_log=None, device="cpu")
        student = job.student(venv)  # what the DAgger parent and every labelling process build
        assert reference.rollout_buffer.buffer_size == 512 and student.rollout_buffer.buffer_size == 2
        assert _buffer_bytes(student) * 256 == _buffer_bytes(reference)
        assert (student.n_steps, student.batch_size) == (reference.n_steps, reference.batch_size) == (512, 128)
        for (name, a), (_, b) in zip(reference.policy.state_dict().items(), student.policy.state_dict().items()):
            assert torch.equal(a, b), name
        reference.save(tmp_path / "reference.zip")
        student.save(tmp_path / "student.zip")
    finally:
        venv.close()
    with zipfile.ZipFile(tmp_path / "reference.zip") as ref, zipfile.ZipFile(tmp_path / "student.zip") as got:
        assert ref.namelist() == got.namelist()
        for member in ref.namelist():
            if member == "data":  # every saved field; the observation space's pickle carries gymnasium's caches
                saved, made = json.loads(got.read(member)), json.loads(ref.read(member))
                for fields in (saved, made):
                    fields["observation_space"].pop(":serialized:")
                assert saved == made
                continue
            assert got.read(member) == ref.read(member), member
    loaded = PPO.load(tmp_path / "student.zip", device="cpu")
    assert (loaded.n_steps, loaded.batch_size) == (512, 128)
