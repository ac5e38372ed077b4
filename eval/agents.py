"""Turn an agent spec from the command line into a :class:`agents.Policy` for a given env.

A spec is one of: a rule-based agent named in ``conf/agent/`` (``pid_paper``, ``always_proceed``); a trained agent
named in ``conf/agent/`` (``ppo_turn``, ``pilotnet``), meaning its shipped reference ``checkpoints/reference/<name>/``,
or with ``:latest`` (``ppo_turn:latest``) your newest run of it; a bare trained kind with no reference of its name
(``ppo``) meaning your newest run of that kind for this env under ``checkpoints/`` (none: an error naming the
references of that kind); or a path to a checkpoint folder or ``.zip``. ``@preset`` and ``+shield`` go after.
Checkpoints are pickles (SB3 zips): load only those you trust."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym

from agents import Policy
from agents.checkpoint import check_sb3_zip, describe_space, read_config_yaml, saved_config
from agents.configs import KIND_DEFAULT, available_agents, kind_default, shipped_agent
from agents.registry import AGENT_KINDS, OPINIONS, agent_params, opinion_problems, trained_kinds
from av_gym.errors import ConfigError
from av_gym.references import checkout_path_hint, reference_root
from conf.check import sensor_overrides  # noqa: F401 - moved below eval (train checks overrides too); used here
from conf.presets import compose_group  # noqa: F401 - used here and imported from here by tests and tools

__all__ = ["AgentPlan", "available_agents", "check_action_space", "check_plan", "check_preset_space", "compose_group",
           "find_checkpoint",
           "install_opinion", "load_agent_config", "make_eval_env", "plan_agent", "resolve_agent", "sensor_overrides",
           "sensors_summary"]


def load_agent_config(name: str) -> dict[str, Any]:
    """``conf/agent/<name>.yaml`` composed as Hydra composes ``agent=<name>``: its kind's defaults (the kind's
    Params) with the file's values on top; a ``# @package _global_`` variant (it picks its sensors/shield too) is
    composed by Hydra."""
    raw = shipped_agent(name)
    kind = kind_default(raw)
    if "agent" not in raw and kind is not None and all(
            entry in (f"{KIND_DEFAULT}{kind}@_here_", "_self_") for entry in raw.get("defaults", [])):
        values = {k: v for k, v in raw.items() if k != "defaults"}
        return {**AGENT_KINDS.get(kind).Params().as_dict(), **values}
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    if GlobalHydra.instance().is_initialized():
        composed = compose(config_name="train", overrides=[f"agent={name}"])
    else:
        with initialize_config_module("conf", version_base="1.3"):
            composed = compose(config_name="train", overrides=[f"agent={name}"])
    return OmegaConf.to_container(composed.agent, resolve=True)


def _checkpoint_name(kind: str) -> str:
    """The model file a trained kind's trainer writes in ``checkpoints/<run>/`` (its AgentKind's ``checkpoint``)."""
    return AGENT_KINDS.get(kind).checkpoint


LATEST = ":latest"  # `ppo_turn:latest`: your newest run of that agent config, not its shipped reference


def split_latest(spec: str) -> tuple[str, bool]:
    """``("ppo_turn", True)`` for ``ppo_turn:latest``, ``("ppo_turn", False)`` for ``ppo_turn``."""
    spec = str(spec)
    return (spec[: -len(LATEST)], True) if spec.endswith(LATEST) else (spec, False)


def find_checkpoint(kind: str, env_name: str, root: str | Path, name: str | None = None,
                    latest: bool = False, reference: str | Path | None = None) -> Path:
    """The checkpoint an agent spec means, the same on every day and in every clone:

    - a named agent (``name``, e.g. ``ppo_turn``) is its shipped reference, ``checkpoints/reference/<name>/``,
      whatever you trained since (a name that meant "the newest run" evaluated a 4-minute run under the row label
      of the reference);
    - ``latest=True`` (the spec ``ppo_turn:latest``) is your newest ``checkpoints/<run>/`` whose saved config
      trained that agent config (or, without a name, that ``kind``) on ``env_name``; none is an error, never a
      silent fall-back to the reference;
    - a trained kind that has a reference folder of its own name (``pilotnet``) is that named agent;
    - a bare trained kind with none (``ppo``, ``dagger``) is your newest run of that kind trained on ``env_name``;
      with no run of your own it is an error naming the references of that kind for ``env_name`` (several
      references share a kind: none of them is "the" ``ppo``).

    Reference folders are never searched or ordered by modification time: a name means one folder, and extra
    training seeds of a reference (``reference/seeds/<name>/s<seed>/``, whose configs say ``name: ppo_turn`` too)
    are reached by their path only. The references are the harness's own (:data:`REFERENCE`, or ``reference``
    where a test gives a stand-in), never ``<root>/reference`` of the working folder: a user's
    ``checkpoints/reference/pilotnet`` is evaluated by its path, labelled so."""
    def matches(cfg_path: Path) -> Path | None:
        cfg = read_config_yaml(cfg_path)
        model = cfg_path.parent / _checkpoint_name(kind)
        agent = cfg.get("agent", {})
        if model.is_file() and cfg.get("env", {}).get("name") == env_name and agent.get("kind") == kind \
                and (name is None or agent.get("name") == name):
            return model
        return None

    reference = Path(reference) if reference is not None else REFERENCE
    if name is None and (reference / kind / "config.yaml").is_file():
        name = kind  # `pilotnet`: a kind whose reference folder bears its name is that named agent
    what = name or kind
    if name is not None and not latest:
        own = reference / name / "config.yaml"
        if own.is_file() and matches(own) is not None:
            _note_lookalike(Path(root) / "reference" / name, reference / name)
            return matches(own)
        drives = _scenarios_of(what, kind)
        if env_name not in drives:  # no train command to suggest: train refuses it too
            raise ConfigError(f"{what} drives {list(drives)}, not env={env_name}: there is no {what} checkpoint for "
                              f"it; pick an agent for env={env_name} or pass a checkpoint path")
        where = f"{reference / name}/" if reference.is_dir() else \
            f"{reference}/ does not exist: this install lost its shipped agents; reinstall av-gym"
        raise ConfigError(f"no shipped reference checkpoint for {name!r} on env {env_name!r} ({where}); for your "
                          f"newest run say {name}{LATEST}, or pass a checkpoint path")
    runs = [m for m in map(matches, Path(root).glob("*/config.yaml")) if m is not None]
    if runs:  # your own training runs: the newest
        return max(runs, key=lambda p: p.stat().st_mtime)
    drives = _scenarios_of(what, kind)
    if env_name not in drives:  # no train command to suggest: train refuses it too
        raise ConfigError(f"{what} drives {list(drives)}, not env={env_name}: there is no {what} checkpoint for it; "
                          f"pick an agent for env={env_name} or pass a checkpoint path")
    if latest:
        raise ConfigError(f"{what}{LATEST}: you have no {what} run for env {env_name!r} under {root}/; train one with "
                          f"`{train_command()} env={env_name} agent={what}`, or say {what} for its shipped reference")
    named = sorted(p.parent.name for p in reference.glob("*/config.yaml") if matches(p) is not None)
    hint = f"name a reference of kind {kind} for it ({', '.join(named)}), " if named else ""
    raise ConfigError(f"no {what} checkpoint of your own for env {env_name!r} under {root}/ ({what} is a kind, "
                      f"not a named agent): {hint}train one with `{train_command()} env={env_name} agent={what}`, or "
                      f"pass a checkpoint path")


def train_command() -> str:
    """The training command that works where the user is, for a refusal to suggest: ``python -m train`` in the
    folder holding the harness (a checkout's root, where ``train/`` is found), the console script ``av-gym-train``
    anywhere else (a wheel's harness, or another folder, where ``python -m train`` finds no such module)."""
    root = Path(__file__).resolve().parents[1]  # the folder holding conf/, agents/, train/, eval/
    try:
        here = Path.cwd().resolve()
    except OSError:  # the working folder was removed
        return "av-gym-train"
    return "python -m train" if here == root and root.name != "av_gym_harness" else "av-gym-train"


REFERENCE = reference_root()
"""The shipped reference checkpoints: the checkout's ``checkpoints/reference/``, or the wheel's copy."""


_NOTED: set[tuple[str, str]] = set()
"""The lookalike folders already noted in this process: the command-line check and the job both find the
checkpoint, and the note is said once."""


def _note_lookalike(local: Path, shipped: Path) -> None:
    """One line on stderr when the working folder holds a ``checkpoints/reference/<name>`` of its own (an export of
    yours, say) that the name does not mean: the row is the shipped reference's, and yours is evaluated by its
    path. In the checkout run from its root the two are one folder and nothing is said; said once per process."""
    import sys

    try:
        same = local.resolve() == shipped.resolve()
    except OSError:
        same = True
    key = (str(local), str(shipped))
    if local.is_dir() and not same and key not in _NOTED:
        _NOTED.add(key)
        print(f"[eval] note: {local}/ is not the shipped reference {local.name!r} ({shipped}/), which the name "
              f"means; to evaluate yours pass its path: agents=[{local}]", file=sys.stderr)


def _scenarios_of(what: str, kind: str) -> tuple[str, ...]:
    """The scenarios agent config (or kind) ``what`` can drive: its ``scenarios``, else its kind's default."""
    if what in available_agents():
        return tuple(load_agent_config(what).get("scenarios") or ())
    return tuple(AGENT_KINDS.get(kind).Params().scenarios) if kind in AGENT_KINDS else ()


def _check_scenario(label: str, cfg: dict, env_name: str) -> None:
    if env_name not in cfg.get("scenarios", [env_name]):
        raise ConfigError(f"agent {label!r} drives scenarios {cfg['scenarios']}, not {env_name!r}")


def _checkpoint_file(path: Path, env_name: str) -> tuple[str, Path]:
    """(kind, model file) of a checkpoint folder (its config.yaml says the kind) or a model file (its suffix
    does), checked without loading it: the file exists and was trained on ``env_name``."""
    loadable = trained_kinds()
    if not path.exists():  # a checkout's path from the docs, given where there is none (a wheel): say where it is
        raise ConfigError(f"checkpoint {str(path)!r}: no such file or folder{checkout_path_hint(path)}")
    if path.is_dir():
        cfg_path = path / "config.yaml"
        kind = read_config_yaml(cfg_path).get("agent", {}).get("kind") if cfg_path.is_file() else "ppo"
        if kind not in loadable:
            raise ConfigError(f"checkpoint folder {str(path)!r} holds agent kind {kind!r}; loadable: {loadable}")
        model_path = path / _checkpoint_name(kind)
    else:
        model_path = path
        kind = next((k for k in loadable if Path(_checkpoint_name(k)).suffix == path.suffix), None)
        if kind is None:  # each file name once (several kinds share model.zip)
            raise ConfigError(f"checkpoint {str(path)!r}: unknown file type; expected a checkpoint folder or one of "
                              f"{list(dict.fromkeys(_checkpoint_name(k) for k in loadable))}")
    if not model_path.is_file():
        raise ConfigError(f"checkpoint {str(model_path)!r} does not exist")
    if model_path.suffix == ".zip":  # empty, truncated or corrupt: one line now, not a traceback from SB3 later
        check_sb3_zip(model_path)
    cfg_path = model_path.parent / "config.yaml"
    if cfg_path.is_file():
        saved_env = read_config_yaml(cfg_path).get("env", {}).get("name")
        if saved_env != env_name:
            raise ConfigError(f"checkpoint {str(model_path)!r} was trained on env {saved_env!r}, not {env_name!r}")
    return kind, model_path


def _load_trained(path: Path, env: gym.Env, env_name: str) -> Policy:
    kind, model_path = _checkpoint_file(path, env_name)
    return AGENT_KINDS.get(kind).load(model_path, env)


def _is_path(spec: str) -> bool:
    return bool(Path(spec).suffix) or "/" in spec or Path(spec).is_dir()


def check_plan(plan: "AgentPlan", env_name: str) -> None:
    """Everything about a plan that can be checked without building its env: the checkpoint file (exists, same
    env) and the sensors and shield it will run with (a checkpoint's saved ones included)."""
    from conf.check import section_problems

    if _is_path(plan.spec):
        _checkpoint_file(Path(plan.spec), env_name)
    for group, section in (("sensors", plan.sensors), ("shield", plan.shield)):
        problems = section_problems(group, section)
        if group == "shield" and isinstance(section, dict):  # the opinion it names is the harness's to install
            problems += opinion_problems(section.get("second_opinion", "none"))
        if problems:
            raise ConfigError(f"agent {plan.given!r}: {problems[0]}")


def resolve_agent(spec: str, env: gym.Env, env_name: str, checkpoints: str | Path) -> tuple[str, Policy]:
    """``(label, policy)`` for one agent spec on ``env`` (the env instance the policy will drive): a trained kind
    (:func:`find_checkpoint`), a checkpoint path, or an agent config of ``conf/agent/`` (a rule-based kind builds
    its policy, a trained one loads its shipped reference, or with ``:latest`` your newest run of it)."""
    spec = str(spec)
    name, latest = split_latest(spec)
    if name in trained_kinds():
        path = find_checkpoint(name, env_name, checkpoints, latest=latest)
        print(f"[eval] {spec}: using {path}")
        return spec, _load_trained(path, env, env_name)
    if _is_path(spec):
        path = Path(spec)
        label = path.parent.name if path.suffix else path.name
        return label, _load_trained(path, env, env_name)
    cfg = load_agent_config(name)
    _check_scenario(name, cfg, env_name)
    params = agent_params(cfg, where=f"agent {name!r}: agent")
    kind = AGENT_KINDS.get(params.kind)
    if latest and not kind.trained():
        raise ConfigError(f"agent {spec!r}: {name!r} is rule-based, it has no runs; say {name}")
    if kind.trained():  # a named trained agent: its shipped reference (name:latest: your newest run of it)
        path = find_checkpoint(params.kind, env_name, checkpoints, name=None if name == params.kind else name,
                               latest=latest)
        print(f"[eval] {spec}: using {path}")
        return spec, _load_trained(path, env, env_name)
    return spec, kind.build(params, env, spec)


def make_eval_env(env_cfg: dict, sensors: dict | None, shield: dict | None, **kwargs: Any) -> gym.Env:
    """:func:`av_gym.make.make_env`, with the AEB shield's second opinion installed (:func:`install_opinion`)."""
    from av_gym.make import make_env

    env = make_env(env_cfg, sensors, shield, **kwargs)
    install_opinion(env)
    return env


def install_opinion(env: gym.Env) -> None:
    """The second opinion the AEB shield's config names (``shield.second_opinion``), resolved here by
    :data:`agents.registry.OPINIONS` and built from the agent config of that name: the library's shield takes an
    object (:class:`av_gym.shields.Opinion`), it knows no harness names. An opinion already installed is kept."""
    from av_gym.shields import find_shield

    aeb = find_shield(env)
    name = getattr(getattr(aeb, "p", None), "second_opinion", "none")
    if aeb is None or name == "none" or aeb.opinion is not None:
        return
    problems = opinion_problems(name)
    if problems:
        raise ConfigError(problems[0])
    aeb.opinion = OPINIONS.get(name)(agent_params(load_agent_config(name), where=f"shield.second_opinion {name!r}"))


# ----------------------------------------------------------------------------------------------- per-agent stacks
@dataclass
class AgentPlan:
    """What one agent spec needs: the label in tables (:func:`eval.labels.row_label`: the spec and what the
    command line changed about how it ran), the sensors and shield configs its env is built with, and
    the spec to hand to :func:`resolve_agent` once that env exists. For a trained agent, ``trained_sensors`` are
    the sensors it was trained on (its checkpoint's, or the ``@preset``) and ``sensor_overrides`` the command
    line's ``sensors.*`` changes applied on top of them to give ``sensors`` (dotted path → value). For a rule-based
    agent, ``own_sensors`` is the preset it names for itself (its config's ``sensors:``), which it runs on whatever
    ``sensors=`` says, unless driven from another with ``agent@preset``."""

    label: str
    spec: str
    sensors: dict
    shield: dict
    trained_sensors: dict | None = None
    sensor_overrides: dict = field(default_factory=dict)
    own_sensors: str | None = None
    given: str = ""  # the spec as the command line gave it (``label`` adds what it changed): "" means ``label``

    def __post_init__(self) -> None:
        self.given = self.given or self.label


def _with_overrides(label: str, base: dict, overrides: dict[str, Any], whose: str = "it was trained with") -> dict:
    """``base`` sensors (a trained agent's, or the ``@preset`` of a rule-based one: ``whose`` says which) with the
    command line's ``overrides`` applied. An override of a sensor the agent's stack does not have would add an
    observation key, so it is refused."""
    import copy

    out = copy.deepcopy(base)
    for path, value in overrides.items():
        keys = path.split(".")
        if len(keys) > 1 and not isinstance(out.get(keys[0]), dict):
            have = [k for k, v in out.items() if isinstance(v, dict)]
            raise ConfigError(f"sensors.{path}={value!r}: agent {label!r} runs on the sensors {whose} "
                              f"({base.get('name')!r}: {have}), which have no {keys[0]!r}; that would change its "
                              f"observation space")
        node = out
        for k in keys[:-1]:
            if not isinstance(node.get(k), dict):
                node[k] = {}
            node = node[k]
        node[keys[-1]] = copy.deepcopy(value)
    return out


def observation_space(env_cfg: Any, sensors: dict) -> gym.Space:
    """The observation space of the per-env stack ``env_cfg`` + ``sensors`` (built, read and closed)."""
    from av_gym.make import make_env

    env = make_env(env_cfg, sensors, None)
    try:
        return env.observation_space
    finally:
        env.close()


def check_preset_space(plan: AgentPlan, env_cfg: Any) -> None:
    """Refuse (one line, before any episode) ``agent@preset`` for a trained agent whose checkpoint was trained on
    sensors of another observation space (its config.yaml's): its policy's own check comes when it is loaded, after
    the agents listed before it have run and written their rows."""
    agent, _, preset = plan.given.partition("+")[0].partition("@")
    own = saved_config(Path(plan.spec)).get("sensors") if preset and plan.trained_sensors is not None else None
    if not own:
        return
    given, trained = observation_space(env_cfg, plan.sensors), observation_space(env_cfg, own)
    if given != trained:
        raise ConfigError(f"agent {plan.given!r}: @{preset} gives observations {describe_space(given)}, but it was "
                          f"trained on sensors={own.get('name')}, {describe_space(trained)}; drive it from a preset "
                          f"with that observation space ({agent}@{own.get('name')}, or {agent} alone)")


_ACTION_PROBLEMS: dict[str, str | None] = {}  # _first_action_problem's answers: agent+aeb is agent's (0.5-1 s a load)


def _first_action_problem(plan: AgentPlan, env_cfg: dict, checkpoints: str | Path) -> str | None:
    """Why agent ``plan`` cannot drive the env ``env_cfg`` (None: it can): its policy built (a checkpoint loaded) on
    its sensors, reset with seed 0 and asked for its first action, which must be in the env's action space
    (:func:`av_gym.actions.check_action`, the env's own check). Without the shield, which takes the env's actions."""
    import json

    from av_gym.actions import check_action
    from av_gym.make import make_env

    key = json.dumps([plan.spec, plan.sensors, env_cfg, str(checkpoints)], sort_keys=True, default=str)
    if key in _ACTION_PROBLEMS:
        return _ACTION_PROBLEMS[key]
    env, problem = None, None
    try:
        env = make_env(env_cfg, plan.sensors, None)
        obs, _ = env.reset(seed=0)
        _, policy = resolve_agent(plan.spec, env, env_cfg["name"], checkpoints)
        policy.reset()
        check_action(env.action_space, policy.act(obs))
    except ConfigError as exc:  # InvalidAction is one; so is a checkpoint trained on another action space
        problem = str(exc)
    finally:
        if env is not None:
            env.close()
    _ACTION_PROBLEMS[key] = problem
    return problem


def check_action_space(plan: AgentPlan, env_cfg: dict, checkpoints: str | Path) -> None:
    """Refuse (one line, before any episode) an agent whose actions the env does not take: otherwise the agents
    listed before it run and write their rows first and its first step fails (``gap_acceptance`` gives
    meta-actions, ``env.action=continuous`` takes accelerations). The line names the agent, the ``env.action``
    given and the values it can drive (each tried the same way). An agent that drives no ``env.action`` has
    another problem (a damaged checkpoint, another scenario's agent): not this check's, so left to the checks and
    the job that say it where they always have (a sweep's job failing alone, the other cells run)."""
    import typing

    from av_gym.make import scenario_params

    problem = _first_action_problem(plan, env_cfg, checkpoints)
    if problem is None:
        return
    params = scenario_params(env_cfg)
    values = typing.get_args(typing.get_type_hints(type(params)).get("action")) if hasattr(params, "action") else ()
    given = getattr(params, "action", None)
    works = [v for v in values if v != given and _first_action_problem(plan, {**env_cfg, "action": v},
                                                                         checkpoints) is None]
    if not works:
        return
    raise ConfigError(f"agent {plan.given!r} cannot drive env.action={given}: {problem}; it drives "
                      f"env.action={' or '.join(works)}")


def check_sensor_overrides(plan: AgentPlan, env_cfg: Any) -> None:
    """Refuse (one line naming the field) command-line sensor overrides that change the observation space a
    trained agent was trained on: its env is built with and without them and the spaces compared."""
    if plan.trained_sensors is None or not plan.sensor_overrides:
        return
    trained = observation_space(env_cfg, plan.trained_sensors)
    if observation_space(env_cfg, plan.sensors) == trained:
        return
    for path, value in plan.sensor_overrides.items():  # name the first override that changes it on its own
        alone = observation_space(env_cfg, _with_overrides(plan.given, plan.trained_sensors, {path: value}))
        if alone != trained:
            raise ConfigError(f"sensors.{path}={value!r} changes the observation space of agent {plan.given!r} "
                              f"from {describe_space(trained)} to {describe_space(alone)}; a trained agent can only "
                              f"run with settings that keep it")
    raise ConfigError(f"sensors overrides {sorted(plan.sensor_overrides)} together change the observation space of "
                      f"agent {plan.given!r}; a trained agent can only run with settings that keep it")


def plan_agent(spec: str, env_name: str, sensors: dict, shield: dict, checkpoints: str | Path) -> AgentPlan:
    """Decide how agent ``spec`` runs. ``agent+shield`` (e.g. ``always_proceed+aeb``) wraps it in
    ``conf/shield/<shield>.yaml``. An agent runs with its own sensors when it has them (a rule-based agent's
    ``sensors:`` field; a checkpoint's training config), else with the ``sensors`` given; the privileged
    ``truth`` state is what PID on the paper's simulator CTE needs, images are what PilotNet needs.

    A trained agent's sensors are the base and the command line's ``sensors.*`` overrides (the fields of
    ``sensors`` that differ from its shipped preset, :func:`sensor_overrides`) are applied on top, so
    ``sensors.cameras.night=true`` reaches PilotNet; an override of a sensor its stack lacks is refused here, one
    that changes its observation space by :func:`check_sensor_overrides` (which needs the env config).

    ``agent@preset`` runs the agent on another sensors preset than its own (``ppo_turn@turn_perceived``: a policy
    trained on privileged objects, driven from tracked detections); the observation spaces must match. A rule-based
    agent's ``@preset`` gets the command line's overrides as a trained agent's sensors do
    (``gap_acceptance@turn_perceived sensors=turn_perceived sensors.detector.miss_rate=0.5``)."""
    base, _, shield_name = str(spec).partition("+")
    if "@" in shield_name:  # ppo_turn+aeb@turn_perceived: the preset would be read as part of the shield's name
        shield_name, _, late = shield_name.partition("@")
        raise ConfigError(f"agent {spec!r}: @preset goes before +shield: {base}@{late}+{shield_name}")
    base, _, preset = base.partition("@")
    base, latest = split_latest(base)
    if shield_name and (shield or {}).get("name") != shield_name:  # the command line's own, with its overrides
        shield = compose_group("shield", shield_name)
    forced = compose_group("sensors", preset) if preset else None
    overrides = sensor_overrides(sensors)  # before `sensors` is replaced by an agent's own preset below

    def trained_plan(run_spec: str, path: Path) -> AgentPlan:
        own = forced or saved_config(path).get("sensors")
        if own is None:  # a checkpoint without its config: it runs on the sensors given
            return _labelled(AgentPlan(str(spec), run_spec, sensors, shield), _default_preset(sensors))
        return _labelled(AgentPlan(str(spec), run_spec, _with_overrides(str(spec), own, overrides), shield, own,
                                   overrides), own)

    if base in trained_kinds() or _is_path(base):
        path = find_checkpoint(base, env_name, checkpoints, latest=latest) if base in trained_kinds() else Path(base)
        return trained_plan(str(path) if base in trained_kinds() else base, path)
    cfg = load_agent_config(base)
    if latest and cfg.get("kind") not in trained_kinds():
        raise ConfigError(f"agent {spec!r}: {base!r} is rule-based, it has no runs; say {base}")
    baseline = compose_group("sensors", cfg["sensors"]) if cfg.get("sensors") else _default_preset(sensors)
    if cfg.get("sensors") and (sensors or {}).get("name") != cfg["sensors"]:
        # the agent's own preset, unless the one given is that preset (then with the command line's overrides,
        # e.g. a sweep over sensors.gnss.sigma for pid_gnss)
        sensors = compose_group("sensors", cfg["sensors"])
    if cfg.get("kind") in trained_kinds():
        path = find_checkpoint(cfg["kind"], env_name, checkpoints, name=None if base == cfg["kind"] else base,
                               latest=latest)
        return trained_plan(str(path), path)
    if forced:  # the command line's sensors.* overrides reach a rule-based agent's @preset as a trained one's
        return _labelled(AgentPlan(str(spec), base, _with_overrides(str(spec), forced, overrides, f"@{preset} gives"),
                                   shield), forced)
    return _labelled(AgentPlan(str(spec), base, sensors, shield, own_sensors=cfg.get("sensors")), baseline)


def _default_preset(sensors: dict | None) -> dict | None:
    """The sensors an agent with none of its own runs on when ``sensors=`` is left out: eval's default preset, as
    shipped (None when the caller gave none: it leaves the sensors to the env)."""
    from conf.check import default_sensors

    return None if sensors is None else compose_group("sensors", default_sensors("eval"))


def _labelled(plan: AgentPlan, baseline: dict | None) -> AgentPlan:
    """``plan`` with its row label (:func:`eval.labels.row_label`; ``baseline``: the sensors the bare spec runs on),
    its spec as given kept in ``given``."""
    from eval.labels import row_label

    plan.given, plan.label = plan.label, row_label(plan.label, plan.sensors, baseline, plan.shield)
    return plan


def sensors_summary(sensors: dict | None, group: str = "sensors") -> str:
    """One line: the preset name and every field that differs from the shipped preset (``cameras: night=True``);
    ``group="shield"``: a shield's (``aeb with mode='perceived'``)."""
    if not sensors:
        return "none"
    name = sensors.get("name", "?")
    changed = sensor_overrides(sensors, group)
    return f"{name}" + (f" with {', '.join(f'{k}={v!r}' for k, v in changed.items())}" if changed else
                        " (as shipped)")
