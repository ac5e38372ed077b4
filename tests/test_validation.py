"""The config checker (conf/check.py, every section against its kind's Params): every shipped option passes, every
field refuses a bad value with a line naming it. In-process and fast; the command-line behaviour (one line, exit 2,
nothing written) is in test_cli.py, the Params checker itself in test_params.py."""

from __future__ import annotations

import functools
from importlib import resources

import pytest
import yaml

from conf.check import check_command_line, problems
from av_gym.errors import ConfigError


def options(group: str) -> list[str]:
    return sorted(p.name[:-5] for p in (resources.files("conf") / group).iterdir() if p.name.endswith(".yaml"))


def scenario_of(agent: str) -> str:
    raw = yaml.safe_load((resources.files("conf") / "agent" / f"{agent}.yaml").read_text())
    return raw.get("scenarios", raw.get("agent", {}).get("scenarios", ["left_turn"]))[0]  # or a global package


SHIPPED = ([("train", [f"env={e}"]) for e in options("env")]
           + [("train", [f"agent={a}", f"env={scenario_of(a)}"]) for a in options("agent")]
           # the default agent (ppo_turn) decides go/yield from obs['turn']: other presets are checked with a
           # driver that needs no particular observation (the pair is refused, rightly: conf/check.py)
           + [("train", [f"sensors={s}"] + ([] if s.startswith("turn_") else ["agent=always_proceed"]))
              for s in options("sensors")]
           + [("train", [f"shield={s}"]) for s in options("shield")]
           + [("eval", []), ("eval", ["env=lane_keeping"])])


def composed(command: str, overrides: list[str]) -> dict:
    """The checked config of ``python -m <command> <overrides>`` as plain containers: a copy the test may change."""
    import copy

    return copy.deepcopy(_composed(command, tuple(overrides)))


@functools.lru_cache(maxsize=None)
def _composed(command: str, overrides: tuple[str, ...]) -> dict:
    # Hydra's composition costs ~0.3 s a config; several tests compose the same one
    from omegaconf import OmegaConf

    (cfg,) = check_command_line(command, list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


# One shipped option per kind of section is composed and checked in the fast suite (each agent kind's first preset,
# both scenarios, the sensors presets that hold every sensor and every turn feature, the plain and the second-opinion
# shield, eval's config); the other presets repeat those Params and are slow (Hydra's composition, ~0.3 s each, and
# the wrong-type check per leaf, ~0.3 s more).
EVERY_FIELD_FAST = {("train", ("env=lane_keeping",)), ("train", ("env=left_turn",)), ("eval", ()),
                    *(("train", (f"agent={a}", "env=left_turn")) for a in (
                        "always_proceed", "belief_lookahead", "dagger_turn", "gap_acceptance", "lookahead",
                        "pid_paper", "pilotnet")),
                    ("train", ("sensors=full", "agent=always_proceed")), ("train", ("sensors=turn_perceived_memory",)),
                    ("train", ("shield=aeb",)), ("train", ("shield=aeb_belief",))}


def fast_or_slow(command: str, overrides: list[str]):
    """The shipped options checked in the fast suite: EVERY_FIELD_FAST; the rest in the slow one."""
    return pytest.param(command, overrides, marks=() if (command, tuple(overrides)) in EVERY_FIELD_FAST
                        else pytest.mark.slow)


@pytest.mark.parametrize("command, overrides", [fast_or_slow(c, o) for c, o in SHIPPED])
def test_every_shipped_option_is_valid(command, overrides):
    assert problems(composed(command, overrides), command) == []


def leaves(cfg, path=()):
    if isinstance(cfg, dict):
        for k, v in cfg.items():
            yield from leaves(v, (*path, k))
    else:
        yield path, cfg


def set_at(cfg: dict, path: tuple, value) -> None:
    for k in path[:-1]:
        cfg = cfg[k]
    cfg[path[-1]] = value


@pytest.mark.parametrize("command, overrides", [fast_or_slow(c, o) for c, o in SHIPPED])
def test_every_field_refuses_a_value_of_the_wrong_type_naming_the_field(command, overrides):
    """No field goes unchecked: each leaf of each shipped option, given a value of the wrong type, is refused by
    a message that starts with its dotted name."""
    import copy

    base = composed(command, overrides)
    unchecked = []
    for path, value in leaves(base):
        if path[:2] == ("agent", "search"):  # a record of how the PID gains were found; never read
            continue
        cfg = copy.deepcopy(base)
        bad = 12345 if isinstance(value, str) else "abc"
        set_at(cfg, path, bad)
        found = problems(cfg, command)
        name = ".".join(map(str, path))
        if not any(p.startswith(name) for p in found):
            unchecked.append((name, found[:1]))
    assert unchecked == []


@pytest.mark.parametrize("path, value, needle", [
    (("sensors", "gnss", "sigma"), -0.5, "sensors.gnss.sigma must be a number >= 0, got -0.5"),
    (("sensors", "imu", "gyro_sigma"), -1, "sensors.imu.gyro_sigma must be a number >= 0"),
    (("sensors", "lidar", "dropout"), 1.2, "sensors.lidar.dropout must be a number in [0, 1], got 1.2"),
    (("sensors", "lidar", "range_sigma"), float("nan"), "sensors.lidar.range_sigma must be a number >= 0, got nan"),
    (("sensors", "detector", "miss_rate"), -0.1, "sensors.detector.miss_rate must be a number in [0, 1)"),
    (("sensors", "cameras", "noise", "pixel_std"), -3, "sensors.cameras.noise.pixel_std must be a number >= 0"),
    (("sensors", "cameras", "noise", "contrast"), 1.5, "sensors.cameras.noise.contrast must be a number in [0, 1)"),
    (("sensors", "localizer", "noise"), {"gate_prob": 1.0}, "sensors.localizer.noise.gate_prob must be a number in (0, 1)"),
    (("sensors", "localizer", "noise"), {"gnss_sigmaa": 1.0}, "sensors.localizer.noise.gnss_sigmaa is not"),
    (("sensors", "gnss", "sigmaa"), 1.0, "sensors.gnss.sigmaa is not a parameter of GNSS; allowed: ["),
    (("sensors", "gnss", "outage"), "sometimes", "sensors.gnss.outage must be one of ['none', 'random', 'scripted']"),
    (("sensors", "gnss", "outage_windows"), [[1, 2, 3]], "sensors.gnss.outage_windows[0] must be a list of 2 items"),
    (("env", "spawn_probability"), 1.01, "env.spawn_probability must be a number in [0, 1]"),
    (("env", "fast"), "yes", "env.fast must be true or false, got 'yes'"),
    (("env", "duration"), True, "env.duration must be a number in (0, 600], got True"),
    (("seed",), 1.5, "seed must be an integer in [0, 2147483647], got 1.5"),
    (("run_name",), "a/b", "run_name must be a folder name"),
])
def test_bad_values_name_the_field_and_what_is_allowed(path, value, needle):
    cfg = composed("train", ["sensors=full", "+sensors.localizer={}", "agent=always_proceed"])
    set_at(cfg, path, value)
    found = problems(cfg, "train")
    assert found and needle in found[0], found


def test_shield_probability_and_agent_kind():
    cfg = composed("eval", ["shield=aeb"])
    cfg["shield"]["detector"]["miss_rate"] = 1.0
    assert problems(cfg, "eval")[0].startswith("shield.detector.miss_rate must be a number in [0, 1)")
    cfg = composed("train", [])
    cfg["agent"]["kind"] = "sac"
    (line,) = problems(cfg, "train")
    from agents.registry import AGENT_KINDS

    assert line == f"agent.kind must be one of {AGENT_KINDS.names()}, got 'sac'" and "'ppo'" in line


@pytest.mark.parametrize("argv, needle", [
    (["agent.epoch=3"], "agent.epoch is not a field of agent=ppo_turn; allowed: ['action_repeat', 'actions',"),
    (["env=foo"], "env=foo: env must be one of ['lane_keeping', 'left_turn']"),
    (["env.foo.bar=1"], "env.foo is not a field of env=left_turn; allowed: ['acceleration_range'"),
    (["seed.x=1"], "seed is a value, not a section"),
    (["seed=abc"], "seed must be an integer in [0, 2147483647], got 'abc'"),
    (["seed=[1"], "cannot parse the command line"),
    (["-m", "seed=0,1", "env.duration=5,-5"], "env.duration must be a number in (0, 600], got -5"),
])
def test_command_line_problems_are_one_line(argv, needle):
    with pytest.raises(ConfigError) as err:
        check_command_line("train", argv)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_a_sweep_is_checked_value_by_value():
    assert len(check_command_line("train", ["-m", "seed=0,1,2", "env.duration=5,6"])) == 1 + 2 + 1


def test_hydra_options_are_left_to_hydra():
    assert check_command_line("train", ["--cfg", "job"]) == []


def test_pilotnet_weights_load_without_unpickling_code(monkeypatch):
    import torch

    from agents import pilotnet

    seen = {}
    real = torch.load

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(torch, "load", spy)
    pilotnet.load_policy(resources.files("conf").parent / "checkpoints" / "reference" / "pilotnet"
                         / "model.pt")
    assert seen.get("weights_only") is True


def test_readme_says_a_checkpoint_is_code_and_must_be_trusted():
    text = (resources.files("conf").parent / "README.md").read_text().lower()
    assert "checkpoint is code" in text and "pickle" in text and "trust" in text


def test_numbers_are_finite():
    from av_gym.params import check
    from av_gym.sensors.gnss import GNSSParams

    assert check(GNSSParams, {"sigma": float("inf")}) and check(GNSSParams, {"latency": float("nan")})
    assert not check(GNSSParams, {"sigma": 1})


def test_a_command_line_is_composed_once_and_checked_once(tmp_path, monkeypatch):
    """``python -m eval``: the check before Hydra composes the command line once and checks the config once; the
    job Hydra then runs from it is not checked again, and no env is built before the episodes'."""
    import sys

    import hydra

    import av_gym.make
    import conf.check
    from eval import __main__ as eval_main

    calls = {"compose": 0, "problems": 0, "make_env": 0}

    def counted(name, real):
        def call(*args, **kwargs):
            calls[name] += 1
            return real(*args, **kwargs)
        return call

    monkeypatch.setattr(hydra, "compose", counted("compose", hydra.compose))
    monkeypatch.setattr(conf.check, "problems", counted("problems", conf.check.problems))
    checked = {}

    def first_env(*args, **kwargs):  # the first env built: by then every check has run
        checked.setdefault("problems", calls["problems"])
        return real_make_env(*args, **kwargs)

    real_make_env = av_gym.make.make_env
    monkeypatch.setattr(av_gym.make, "make_env", first_env)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["eval", "agents=[always_proceed]", "episodes=1", "out_dir=out",
                                      "progress_bar=false", "hydra.run.dir=hydra_run"])
    eval_main.main()
    assert (tmp_path / "out" / "results.csv").is_file()
    assert calls["compose"] == 1 and calls["problems"] == 1 and checked == {"problems": 1}


def test_checking_a_training_config_builds_no_env(monkeypatch):
    """The whole check of ``python -m train``'s config reads the config: no env stack is built to validate it."""
    import av_gym.make
    from train.__main__ import _validate

    (cfg,) = check_command_line("train", ["env=left_turn", "shield=aeb", "env.spawn_probability=0.3",
                                          "agent.vec_env=subproc", "agent.n_envs=2", "agent.n_steps=256"])

    def no_env(*args, **kwargs):
        raise AssertionError("an env was built to check a config")

    monkeypatch.setattr(av_gym.make, "make_env", no_env)
    monkeypatch.setattr(av_gym.make, "make_training_env", no_env)
    _validate(cfg)
