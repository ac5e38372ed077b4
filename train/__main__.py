"""``python -m train [env=left_turn] [agent=ppo] [seed=0] [agent.total_timesteps=...]``

Builds the env stack and the agent from ``conf/``, trains (PPO with stable-baselines3; rule-based agents have
nothing to train), logs to TensorBoard, writes checkpoints atomically under ``checkpoints/<run_name>/`` with the
resolved config beside them, then evaluates the result briefly against the scenario's baseline."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from av_gym.errors import ConfigError, check_folder, folder_problem, run_cli, run_hydra
from conf.commands import TrainCommand, TrainOptions

# What the brief evaluation after training compares the trained agent with (train.baseline: auto): on the left turn
# the do-nothing-clever driver and the two-parameter rule a learned driver must beat.
BASELINES = {"left_turn": ("always_proceed", "gap_acceptance"), "lane_keeping": ("pid_paper",)}


def _kind(cfg: DictConfig):
    """The agent's kind (agents/registry.py AGENT_KINDS): its Params, and for a trained kind its checkpoint."""
    from agents.registry import AGENT_KINDS

    return AGENT_KINDS.get(cfg.agent.get("kind"))


# the trainers that evaluate during training (train.eval_n episodes each time: train/ppo.py, train/dagger.py); a rule
# agent or PilotNet only has the brief evaluation after it (train.eval_episodes)
_EVALUATES_WHILE_TRAINING = ("ppo", "dagger")


def validation_seeds(options: TrainOptions, n: int, count: str = "episodes") -> range:
    """``n`` seeds of the validation split from ``train.eval_seed`` (default: the split's start): the evaluations
    during training pick ``best.zip`` and the one after it is looked at, so they may never be test seeds. ``count``
    names the setting ``n`` came from in a refusal."""
    from av_gym.seeds import config_seeds

    return config_seeds("validation", n, options.eval_seed, "train.eval_seed", count)


def _validate(cfg: DictConfig) -> TrainCommand:
    """Every field against the schema (the agent section: its kind's Params), then what its trainer needs: the
    whole check of a training config (the env's, sensors' and shield's sections included: no env is built).
    Returns the command's settings."""
    from conf.check import validate_config

    validate_config(cfg, "train")
    return _check_needs(cfg)


def _check_needs(cfg: DictConfig) -> TrainCommand:
    """What a config whose fields are valid still needs: validation seeds in their split, an agent that drives
    this env, what its trainer checks (train/registry.py ``TRAIN_CHECKS``). Returns the command's settings."""
    from train.registry import train_problems

    command = TrainCommand.of(cfg)
    options = command.train
    agent = cfg.agent
    counts = {"train.eval_episodes": options.eval_episodes}
    if agent.kind in _EVALUATES_WHILE_TRAINING:
        counts["train.eval_n"] = options.eval_n
    count = max(counts, key=counts.__getitem__)  # the larger count reaches farther into the split
    validation_seeds(options, counts[count], count)
    if cfg.env.name not in agent.scenarios:
        raise ConfigError(f"agent {agent.name!r} drives scenarios {list(agent.scenarios)}, not env={cfg.env.name}")
    problems = train_problems(cfg.agent.kind, cfg)
    if problems:
        raise ConfigError(problems[0])
    return command


@dataclass(frozen=True)
class Folders:
    """Where one run writes: Hydra's run folder (logs, results), its TensorBoard folder and its checkpoints."""

    run_dir: Path
    ckpt_dir: Path

    @property
    def tb_dir(self) -> Path:
        return self.run_dir / "tb"


def train(cfg: DictConfig) -> dict:
    """Train and briefly evaluate; returns where things went (``run_dir``, ``tensorboard``, ``checkpoint``)."""
    import torch

    from conf.check import was_checked

    # the command line's check ran in this process for a plain run; not for a sweep's job or a caller from Python
    command = TrainCommand.of(cfg) if was_checked(cfg) else _validate(cfg)
    torch.set_num_threads(command.train.torch_threads)
    folders = _claim_folders(cfg, command)
    model_path = _train_agent(cfg, command, folders)
    if command.train.eval_episodes > 0:
        _brief_evaluation(cfg, command, folders, model_path)
    return _report(folders, model_path)


def _claim_folders(cfg: DictConfig, command: TrainCommand) -> Folders:
    """The run's folders, ours alone (a lock), resumable, or refused; cleared first with train.overwrite; the
    resolved config.yaml beside the checkpoints, the code's commit and versions in the log folder's
    provenance.json (train/provenance.py)."""
    from train.checkpoint import write_text_atomic
    from train.run_folder import LINE_CHECKED, clear_for_overwrite, job_folder_problem, release_all

    run_dir, sweep = Path(HydraConfig.get().runtime.output_dir), HydraConfig.get().mode == RunMode.MULTIRUN
    ckpt_dir = Path(command.paths.checkpoints) / command.run_name
    if sweep:  # jobs of a sweep started in the same second share run_name
        ckpt_dir = ckpt_dir.with_name(f"{ckpt_dir.name}-j{HydraConfig.get().job.num}")
    check_folder(ckpt_dir, "paths.checkpoints")  # one line, not a traceback, if it cannot be
    # the job's folder, known only now for a sweep's job or a ${hydra:...} run dir: checked before anything is
    # written (one the command line checked is not: it saw the folder before Hydra wrote .hydra/ in it)
    flag = "hydra.sweep.dir" if sweep else "hydra.run.dir"
    if run_dir.resolve() not in LINE_CHECKED:
        problem = job_folder_problem(run_dir, ckpt_dir, command.train.resume, command.train.overwrite, flag)
        if problem:
            raise ConfigError(problem)
    claim_run(cfg, command, ckpt_dir, None)  # before config.yaml is written
    release_all(keep=ckpt_dir)
    if command.train.overwrite and not command.train.resume:
        removed = clear_for_overwrite(ckpt_dir, run_dir, flag)
        if removed:
            print(f"[train] train.overwrite=true: removed the previous run's {len(removed)} files and folders")
    write_text_atomic(ckpt_dir / "config.yaml", OmegaConf.to_yaml(config_as_ran(cfg), resolve=True))
    from eval.meta import hydra_overrides
    from train.provenance import record_start

    record_start(run_dir, hydra_overrides(), command.train.resume)  # which code trained it (and each resume)
    return Folders(run_dir, ckpt_dir)


def config_as_ran(cfg: DictConfig) -> DictConfig:
    """The run's config as the agent runs it, for config.yaml: a rule-based agent that names its own sensors preset
    (``agent.sensors``: gap_acceptance's turn_truth) runs on it when ``sensors=`` is the command's default
    (conf/check.py _own_preset_problems lets that pass), so the sensors recorded are the ones it ran with (the brief
    evaluation's ``plan.sensors``: eval.agents.plan_agent), not the default it never saw."""
    if _kind(cfg) is None or _kind(cfg).trained() or not cfg.agent.get("sensors"):
        return cfg
    from eval.agents import plan_agent

    sensors, shield = (OmegaConf.to_container(c, resolve=True) for c in (cfg.sensors, cfg.shield))
    plan = plan_agent(str(cfg.agent.name), str(cfg.env.name), sensors, shield, str(cfg.paths.checkpoints))
    ran = OmegaConf.to_container(cfg, resolve=True)
    ran["sensors"] = plan.sensors
    return OmegaConf.create(ran)


def _train_agent(cfg: DictConfig, command: TrainCommand, folders: Folders) -> Path | None:
    """The agent kind's trainer (train/registry.py; none for a rule-based agent); returns the final checkpoint."""
    from train.registry import trainer_of
    from train.run_folder import discard_if_unstarted

    kind = _kind(cfg)
    if not kind.trained():
        print(f"[train] agent {cfg.agent.name!r} is rule-based: nothing to train")
        return None
    try:
        return trainer_of(cfg.agent.kind)(cfg, folders.ckpt_dir, folders.run_dir, command=command)
    except ConfigError:
        # refused by the trainer before it wrote anything (an agent.init_from that does not fit): the fresh run's
        # config.yaml and provenance.json go too, or the run_name would be refused as taken
        from train.provenance import undo_start

        undo_start(folders.run_dir, command.train.resume)
        if not command.train.resume:
            discard_if_unstarted(folders.ckpt_dir)
        raise


def _brief_evaluation(cfg: DictConfig, command: TrainCommand, folders: Folders, model_path: Path | None) -> None:
    """The trained agent (or the rule-based one) and the baselines on ``train.eval_episodes`` validation seeds,
    into results.csv and results.md in the run folder; Ctrl-C keeps (and writes) every finished episode."""
    from eval.meta import env_as_ran
    from eval.report import write_results

    options, env_name, run_dir = command.train, str(cfg.env.name), folders.run_dir
    env = env_as_ran(OmegaConf.to_container(cfg.env, resolve=True))  # results.md says the env it ran in
    n = options.eval_episodes
    seeds = validation_seeds(options, n)
    baselines = list(BASELINES[env_name]) if options.baseline == "auto" else [options.baseline]
    specs = [str(folders.ckpt_dir), *baselines] if model_path else [str(cfg.agent.name)]
    rows, ran_with, shields = [], {}, {}  # label → the sensors it ran with / the shield it ran behind, in results.md
    title = f"{command.run_name}: brief evaluation, {n} episodes of the validation split (seeds {seeds.start}.." \
            f"{seeds.stop - 1})"
    try:  # rows are appended episode by episode
        for spec in specs:
            _evaluate_spec(cfg, command, folders, spec, seeds, rows, ran_with, shields)
    except KeyboardInterrupt:
        if rows:
            write_results(rows, run_dir, env_name, f"{title} (interrupted after {len(rows)} episodes)",
                          sensors=ran_with, split="validation", shields=shields, env=env)
        print(f"[train] interrupted during the brief evaluation: {len(rows)} episodes measured"
              + (f", in {run_dir}/results.csv" if rows else ""), file=sys.stderr)
        raise
    table = write_results(rows, run_dir, env_name, title, sensors=ran_with, split="validation", shields=shields,
                          env=env)
    print(f"\n[train] brief evaluation on {n} validation seeds ({seeds.start}..{seeds.stop - 1}):\n\n{table}\n")


def _evaluate_spec(cfg: DictConfig, command: TrainCommand, folders: Folders, spec: str, seeds: range, rows: list,
                   ran_with: dict, shields: dict) -> None:
    """One agent of the brief evaluation: on the batch when it trained there, else in worker processes (from ~10
    episodes each: a worker costs a few seconds to start) or in this one; appends its rows to ``rows``, its sensors
    to ``ran_with`` and its shield (if any) to ``shields``, by label."""
    from av_gym.batched.shield import shield_kind
    from av_gym.make import make_env
    from eval.agents import plan_agent, resolve_agent
    from eval.runner import EpisodeJob, run_episodes, run_episodes_parallel

    options, env_name, checkpoints = command.train, str(cfg.env.name), command.paths.checkpoints
    n, progress = options.eval_episodes, options.progress_bar
    sensors, shield, env_cfg = (OmegaConf.to_container(c, resolve=True) for c in (cfg.sensors, cfg.shield, cfg.env))
    plan = plan_agent(spec, env_name, sensors, shield, checkpoints)
    label = trained_label(cfg, plan, sensors) if spec == str(folders.ckpt_dir) else plan.label
    ran_with[label] = plan.sensors
    if shield_kind(plan.shield) != "none":
        shields[label] = plan.shield
    n_envs = min(options.eval_n_envs, n // 10)
    if cfg.agent.get("vec_env") == "batched":  # trained on the batch: evaluated there too, all at once
        from eval.batched import run_episodes_batched

        env = make_env(env_cfg, plan.sensors, plan.shield)
        _, policy = resolve_agent(plan.spec, env, env_name, checkpoints)
        env.close()
        run_episodes_batched(env_cfg, plan, policy, seeds, min(n, 256), label, progress=progress, out=rows)
    elif n_envs > 1:  # each episode depends on its seed only: the same rows as in-process, sooner
        job = EpisodeJob(env_cfg, plan.sensors, plan.shield, plan.spec, env_name, str(checkpoints), label)
        run_episodes_parallel(job, seeds, n_envs, progress=progress, out=rows)
    else:
        env = make_env(env_cfg, plan.sensors, plan.shield)
        _, policy = resolve_agent(plan.spec, env, env_name, checkpoints)
        run_episodes(env, policy, seeds, label, progress=progress, out=rows)
        env.close()


def trained_label(cfg: DictConfig, plan, sensors: dict) -> str:
    """The row label of the agent this run trained: its name (``ppo_turn``, not the checkpoint folder) and what
    it ran with besides (eval/labels.py ``row_label``): ``ppo_turn+aeb`` behind a command-line ``shield=aeb``.
    Its sensors are the ones it trained on (``sensors``, the run's section): no ``@preset`` or changed field."""
    from eval.labels import row_label

    return row_label(str(cfg.agent.name), plan.sensors, sensors, plan.shield)


def _report(folders: Folders, model_path: Path | None) -> dict:
    where = {"run_dir": str(folders.run_dir), "tensorboard": str(folders.tb_dir),
             "checkpoint": str(model_path) if model_path else None, "config": str(folders.ckpt_dir / "config.yaml")}
    print(f"[train] logs:        {folders.run_dir}")
    if model_path:
        print(f"[train] tensorboard: tensorboard --logdir {folders.tb_dir}")
        print(f"[train] checkpoint:  {model_path.resolve()}  (config beside it: config.yaml)")
    return where


def claim_run(cfg: DictConfig, command: TrainCommand, ckpt_dir: Path, runs_dir: Path | None,
              runs_flag: str = "paths.runs/run_name") -> None:
    """The run's folders for this process alone (train/run_folder.py): refused if they hold another run (unless
    resuming or overwriting) or what is not a run's, if a resume does not match the run's config.yaml, or if
    another process trains it."""
    from train.run_folder import claim

    claim(ckpt_dir, runs_dir, command.train.resume, command.train.overwrite,
          {k: OmegaConf.to_container(cfg[k], resolve=True) for k in ("env", "sensors", "shield", "agent")}, runs_flag)


def run_dir_of(cfg: DictConfig, command: TrainCommand, argv: list[str]) -> tuple[Path | None, str]:
    """The folder Hydra will write this run's logs in, and what gave it: ``hydra.run.dir`` as ``argv`` gives it
    (resolved against the run's config; None when it names a value only the running job has), else
    ``paths.runs/run_name`` (conf/train.yaml's ``hydra.run.dir``). ``hydra.run.dir=.`` is the user's own folder."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf.errors import OmegaConfBaseException

    given = [o for o in OverridesParser.create().parse_overrides([a for a in argv if not a.startswith("-")])
             if o.key_or_group == "hydra.run.dir" and not o.is_delete()]
    if not given:
        return Path(command.paths.runs) / command.run_name, "paths.runs/run_name"
    node = OmegaConf.create({**OmegaConf.to_container(cfg, resolve=False), "_run_dir": given[-1].value()})
    try:
        return Path(str(node._run_dir)), "hydra.run.dir"
    except OmegaConfBaseException:  # ${hydra:...}: only the job has it
        return None, "hydra.run.dir"


def _check_command_line() -> None:
    """The command line composed and checked once per config (conf/check.py), where the checkpoints go, and for a
    plain run the run's folders claimed: all before Hydra makes a folder."""
    from conf.check import check_command_line
    from train.run_folder import LINE_CHECKED

    commands = []
    LINE_CHECKED.clear()

    def check(cfg: DictConfig) -> None:  # its fields were checked by check_command_line
        command = _check_needs(cfg)
        # where the checkpoints go, before Hydra makes the run folder (a sweep's -j<n> suffix fits: run_name is
        # bounded in the schema)
        problem = folder_problem(Path(command.paths.checkpoints) / command.run_name, "paths.checkpoints")
        if problem:
            raise ConfigError(problem)
        commands.append(command)

    configs = check_command_line("train", sys.argv[1:], check)
    if len(configs) == 1 and not any(a in ("-m", "--multirun") for a in sys.argv[1:]):
        # before Hydra writes runs/<run_name>/.hydra: a run that is not ours is refused with nothing written; the
        # lock is held by this process until it exits (a sweep's jobs each claim their own -j<n> folder)
        cfg, command = configs[0], commands[0]
        run_dir, runs_flag = run_dir_of(cfg, command, sys.argv[1:])
        claim_run(cfg, command, Path(command.paths.checkpoints) / command.run_name, run_dir, runs_flag)
        if run_dir is not None:
            LINE_CHECKED.add(run_dir.resolve())


@hydra.main(config_path="pkg://conf", config_name="train", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    from conf.run_log import job_logged

    run_cli(job_logged(train), cfg, hydra_run_dir=True)  # the run folder's __main__.log holds what it prints


def main() -> None:
    """Check the command line before Hydra makes a run folder (one line and exit 2 on bad input), then run."""
    from conf.hydra_files import hydra_files_whole

    run_cli(_check_command_line)
    with hydra_files_whole():  # Hydra's .hydra/*.yaml written whole, or one line and no run folder left
        run_hydra(_hydra_main)  # a sweep runs every job, then reports the failed ones


if __name__ == "__main__":
    main()
