"""``python -m eval.interventions`` drives its agent with torch on one thread, as ``python -m eval``'s episodes do
(``eval.runner.single_threaded_torch``): its workers and, with ``--workers 1``, the parent build the agent in
``eval.interventions.build`` (the pool's initializer ``_init`` calls it). Unpinned, torch's default pool (one thread
per core) spins on a busy machine (PilotNet on the cameras: ~7 steps/s instead of ~340 on 2 shared cores) and may sum
a network's matmuls in another order than the evaluated episodes did."""

from __future__ import annotations

import pytest

import eval.agents
from eval.interventions import run
from tests.test_eval_threads import _Acted, _ThreadProbe, two_torch_threads  # noqa: F401  (fixture)

torch = pytest.importorskip("torch")


def test_the_labelled_episodes_act_with_one_torch_thread(two_torch_threads, monkeypatch):  # noqa: F811
    probe = _ThreadProbe()
    monkeypatch.setattr(eval.agents, "resolve_agent", lambda spec, env, env_name, checkpoints: (spec, probe))
    with pytest.raises(_Acted):
        run("always_proceed+aeb", [1_950_000], workers=1, progress=False)
    assert probe.threads == 1
