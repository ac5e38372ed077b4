"""``python -m eval env=left_turn agents='[always_proceed,ppo]' episodes=100 [split=validation|test|train]
[seed=...] [n_envs=2] [vec_env=batched]``

An evaluation owns its ``out_dir`` while it runs, as a training run owns its checkpoints
(:class:`av_gym.atomic.OwnedFolders`: an exclusive ``flock`` on ``out_dir/.lock``): a second ``python -m eval ...
out_dir=X`` is refused in one line, rather than both writing X and the second's rows replacing the first's. With an
``out_dir`` of its own, the run folder Hydra made under ``runs/eval/`` is removed again when it holds only Hydra's
files."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from av_gym.atomic import OwnedFolders
from av_gym.errors import ConfigError, check_folder, discard_hydra_run_dir, folder_problem, run_cli, run_hydra
from conf.check import default_sensors, own_sensors_problem
from conf.commands import EvalCommand
from eval.meta import EvalMeta, exit_status, hydra_overrides

OUT_DIRS = OwnedFolders()  # the out_dirs this process is writing


def _check(cfg: DictConfig) -> EvalCommand:
    """The whole check of an evaluation's config: every field against the schema, then :func:`_check_needs`.
    Returns the command's settings."""
    from conf.check import validate_config

    validate_config(cfg, "eval")
    return _check_needs(cfg)


def _check_needs(cfg: DictConfig) -> EvalCommand:
    """What a config whose fields are valid still needs: a seed range in its split, each agent listed once, the
    agents' plans (their checkpoints and sensors) before any env is built. Returns the command's settings."""
    command = EvalCommand.of(cfg)
    episode_seeds(command)  # the seed range fits its split, before any agent is loaded
    duplicates = sorted({a for a in command.agents if command.agents.count(a) > 1})
    if duplicates:  # one row would pool the same seeds twice and count each episode as two
        raise ConfigError(f"agents lists {duplicates[0]!r} more than once; each agent is one row over the same "
                          f"episode seeds, so list it once")
    _check_plans(_plans(cfg, command), command, _plain(cfg.env), _plain(cfg.sensors))
    return command


def _plans(cfg: DictConfig, command: EvalCommand) -> list:
    """How each agent runs (:func:`eval.agents.plan_agent`): its spec, label, sensors and shield; on the batch,
    the sensors the batch runs it with (:func:`_batched_sensors`)."""
    from eval.agents import plan_agent

    sensors, shield, env_cfg = _plain(cfg.sensors), _plain(cfg.shield), _plain(cfg.env)
    plans = [plan_agent(spec, str(cfg.env.name), sensors, shield, command.paths.checkpoints)
             for spec in command.agents]
    return [_batched_sensors(p, env_cfg) for p in plans] if command.vec_env == "batched" else plans


def _batched_sensors(plan, env_cfg: dict):
    """``plan`` as the batch runs it (:func:`eval.batched.batch_sensors`), which results.md then records:
    ``always_proceed`` reads no observation, and runs on the sensors chosen for it (as the per-env stack does), or
    with the command's default preset (no choice, and no form on the batch) on the batch's own features. Sensors
    chosen for it that the batch cannot run (``sensors=cameras``, overrides of the default) are refused rather than
    recorded as run."""
    import dataclasses

    from av_gym.batched.vec_env import check_batchable
    from eval.agents import sensor_overrides
    from eval.batched import batch_sensors, plan_kind

    if env_cfg.get("name") != "left_turn" or plan_kind(plan) != "always_proceed":
        return plan  # refused or run as planned: check_batched_plan
    given = plan.sensors or {}
    if given.get("name") != default_sensors("eval") or sensor_overrides(given):
        try:  # what the batch can run, on the sensors chosen
            check_batchable(env_cfg, given, plan.shield, with_shield=True)
        except ConfigError as exc:
            raise ConfigError(f"agent {plan.given!r}: {str(exc).replace('agent.vec_env=', 'vec_env=')}") from None
    return dataclasses.replace(plan, sensors=dict(batch_sensors(plan, env_cfg)))


def given_sensors_problem(plan, given: dict) -> str | None:
    """A trained agent runs on the sensors it was trained with (its checkpoint's config.yaml), with the command
    line's ``sensors.*`` overrides on top; a rule-based agent that names its own preset (``gap_acceptance``:
    turn_truth) runs on that. Whether ``sensors=`` (``given``) reaches it is :func:`conf.check.own_sensors_problem`'s
    rule, which train's check shares; ``agent@preset`` has chosen its preset already."""
    trained = (plan.trained_sensors or {}).get("name")
    if "@" in plan.given:
        return None
    return own_sensors_problem(plan.given, trained or plan.own_sensors, given, default_sensors("eval"), "eval",
                               trained=bool(trained))


def _check_plans(plans: list, command: EvalCommand, env_cfg: dict, given: dict) -> None:
    """Each agent's checkpoint (if any) and the sensors it runs with (``given``: the command line's preset);
    with ``vec_env=batched``, what the batched engine cannot run, before any folder."""
    from eval.agents import check_action_space, check_plan, check_preset_space, check_sensor_overrides

    for plan in plans:
        problem = given_sensors_problem(plan, given)
        if problem:
            raise ConfigError(problem)
        check_plan(plan, env_cfg["name"])
        check_sensor_overrides(plan, env_cfg)  # a trained agent's sensors with the command line's on top
        check_preset_space(plan, env_cfg)  # agent@preset: the preset gives the observations it was trained on
        if command.vec_env == "batched":  # first: what the batch cannot run is the more direct answer
            from eval.batched import check_batched_plan

            check_batched_plan(plan, env_cfg)
        check_action_space(plan, env_cfg, command.paths.checkpoints)  # its actions fit env.action


def _plain(section) -> dict:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(section, resolve=True)


def episode_seeds(command: EvalCommand) -> range:
    """The episodes' seeds: ``episodes`` consecutive seeds of ``split`` from ``seed`` (default the split's start);
    ConfigError naming the field when they leave the split (av_gym/seeds.py)."""
    from av_gym.seeds import config_seeds

    return config_seeds(command.split, command.episodes, command.seed, "seed")


def claim_out_dir(command: EvalCommand) -> None:
    """``out_dir`` for this process alone (a lock held until the evaluation ends), then checked again under the
    lock: two evaluations started together both passed the check made before it. One line if another holds it."""
    out_dir = command.out_dir
    OUT_DIRS.claim(out_dir, "out_dir", "another evaluation")
    problem = results_problem(command)
    if problem:
        OUT_DIRS.release(out_dir)
        raise ConfigError(problem)


def evaluate(cfg: DictConfig) -> list[dict]:
    """The evaluation ``cfg`` describes, in ``cfg.out_dir`` (held for this process while it runs); returns its rows."""
    from conf.check import was_checked

    out_dir = str(cfg.out_dir)  # released below whatever happens, a config the check refuses included
    try:
        # the command line's check ran in this process for a plain run; a sweep's job or a caller from Python not
        command = EvalCommand.of(cfg) if was_checked(cfg) else _check(cfg)
        return _evaluate(cfg, command)
    finally:
        OUT_DIRS.release(out_dir)
        _discard_unused_run_dir(out_dir)


def _discard_unused_run_dir(out_dir: str) -> None:
    """With an out_dir of its own, Hydra's run folder (``runs/eval/<env>-<time>/``) is left with only Hydra's files:
    removed, so that ``out_dir=X`` writes X alone. A folder with anything else is kept."""
    try:
        from hydra.core.hydra_config import HydraConfig

        run_dir = Path(HydraConfig.get().runtime.output_dir).resolve()
    except Exception:  # called from Python, not as a Hydra job
        return
    out = Path(out_dir).resolve()
    if out != run_dir and run_dir not in out.parents:
        discard_hydra_run_dir()


def _evaluate(cfg: DictConfig, command: EvalCommand) -> list[dict]:
    """Every agent on the same seeds, its rows written as soon as it is done, then the summary and the figures."""
    plans, env_cfg = _plans(cfg, command), _plain(cfg.env)
    problem = results_problem(command)  # before anything runs: another evaluation's results are not replaced
    if problem:
        raise ConfigError(problem)
    check_folder(command.out_dir, "out_dir", create=True)  # before the first episode: results need somewhere to go
    claim_out_dir(command)  # ours alone until the evaluation ends
    seeds = episode_seeds(command)
    meta = EvalMeta(command.out_dir, _meta_settings(command, seeds), hydra_overrides(), env_cfg)
    try:
        rows = _run_all(plans, command, env_cfg, seeds, meta)
        _figures(plans, command, env_cfg, seeds.start)
    except BaseException as exc:  # Ctrl-C or a failure: meta.json says how it ended and how many rows it kept
        with contextlib.suppress(ConfigError):  # a meta.json that cannot be written must not hide why it ended
            meta.end(exit_status(exc))
        raise
    meta.end(0)
    return rows


def _meta_settings(command: EvalCommand, seeds: range) -> dict:
    """What meta.json records of the command's settings besides its command line (which holds only the
    overrides: a default that changes would change what an old command line means)."""
    return {"split": command.split, "seeds": [seeds.start, seeds.stop - 1], "episodes": command.episodes,
            "agents": list(command.agents), "vec_env": command.vec_env, "n_envs": command.n_envs,
            "workers": command.workers}


def _run_all(plans: list, command: EvalCommand, env_cfg: dict, seeds: range, meta: EvalMeta) -> list[dict]:
    """Every agent's episodes, results.csv / results.md (and ``meta``) written after each agent and on Ctrl-C;
    the summary printed. Returns the rows."""
    from eval.agents import _is_path
    from eval.meta import env_as_ran
    from eval.report import faults_note, faults_total, write_results

    env_name, out_dir, split = env_cfg["name"], command.out_dir, command.split
    title = (f"{env_name} ({env_cfg.get('mode', '')}), {command.episodes} episodes of the {split} split "
             f"(seeds {seeds.start}..{seeds.stop - 1})")
    title = title.replace(" ()", "")
    if command.vec_env == "batched" and command.workers > 1:  # what ran, for the summary (the rows are the same)
        workers = min(command.workers, command.episodes)
        title += f", on the batch in {workers} worker processes of {command.n_envs} episodes each"
    rows, env = [], env_as_ran(env_cfg)  # results.md names the env preset and what the command changed of it
    ran = {p.label: p.spec for p in plans if _is_path(p.spec)}  # trained agents: the checkpoint they resolved to
    for label, path in ran.items():
        print(f"[eval] {label}: {path}")
    for plan in plans:  # every spec is checked before any episode runs
        try:  # rows are appended episode by episode: Ctrl-C keeps (and writes) every finished episode
            _run_agent(plan, command, env_cfg, seeds, rows)
        except KeyboardInterrupt:
            if rows:
                write_results(rows, out_dir, env_name, f"{title} (interrupted after {len(rows)} episodes)",
                              **_ran_with(plans, ran, split, rows), env=env)
                meta.episodes_written, meta.sensor_faults = len(rows), faults_total(rows)
                print(f"[eval] interrupted: the {len(rows)} episodes measured are in {out_dir}/results.csv",
                      file=sys.stderr)
            raise
        # each agent's rows as soon as it is done: an evaluation interrupted or failing later keeps what it measured
        write_results(rows, out_dir, env_name, title, **_ran_with(plans, ran, split, rows), env=env)
        meta.write(len(rows), faults_total(rows))  # rc null: still running (or killed, if it stays so)
    table = write_results(rows, out_dir, env_name, title, **_ran_with(plans, ran, split, rows), env=env)
    print(f"\n{title}\n\n{table}\n" + (f"\n{faults_note(rows)}" if faults_total(rows) else ""))
    print(f"[eval] per-episode rows: {out_dir}/results.csv   summary: {out_dir}/results.md"
          + ("" if meta.kept else f"   run: {out_dir}/meta.json"))
    return rows


def _ran_with(plans: list, checkpoints: dict, split: str, rows: list[dict]) -> dict:
    """``write_results``' keywords for every results.md, an interrupted or failing evaluation's included: the
    sensors, checkpoint and shield of each agent with rows in ``rows`` (the label names the shield and the changed
    sensor fields, :mod:`eval.labels`; these sections give every setting)."""
    from av_gym.batched.shield import shield_kind

    labels = {r["agent"] for r in rows}
    kept = [p for p in plans if p.label in labels]
    return {"sensors": {p.label: p.sensors for p in kept}, "split": split,
            "checkpoints": {label: path for label, path in checkpoints.items() if label in labels},
            "shields": {p.label: p.shield for p in kept if shield_kind(p.shield) != "none"}}


def _run_agent(plan, command: EvalCommand, env_cfg: dict, seeds: range, rows: list) -> None:
    """One agent's episodes, appended to ``rows``: stepped together on the batch (vec_env=batched), shared by
    ``n_envs`` worker processes, or in this process."""
    from eval.agents import make_eval_env, resolve_agent
    from eval.runner import EpisodeJob, run_episodes, run_episodes_parallel

    env_name, checkpoints, progress = env_cfg["name"], command.paths.checkpoints, command.progress_bar
    if command.vec_env == "batched" and command.workers > 1:  # each worker builds the agent: none needed here
        from eval.batched import run_episodes_batched

        run_episodes_batched(env_cfg, plan, None, seeds, command.n_envs, plan.label, progress=progress, out=rows,
                             workers=command.workers, checkpoints=str(checkpoints))
        return
    env = make_eval_env(env_cfg, plan.sensors, plan.shield)
    _, policy = resolve_agent(plan.spec, env, env_name, checkpoints)
    if command.vec_env == "batched":  # n_envs episodes stepped together
        from eval.batched import run_episodes_batched

        env.close()
        run_episodes_batched(env_cfg, plan, policy, seeds, command.n_envs, plan.label, progress=progress, out=rows)
    elif command.n_envs > 1:
        env.close()
        job = EpisodeJob(env_cfg, plan.sensors, plan.shield, plan.spec, env_name, str(checkpoints), plan.label)
        run_episodes_parallel(job, seeds, command.n_envs, progress=progress, out=rows)
    else:
        run_episodes(env, policy, seeds, plan.label, progress=progress, out=rows)
        env.close()


def _figures(plans: list, command: EvalCommand, env_cfg: dict, first_seed: int) -> None:
    """Lane keeping: each agent's lap on the first seed (CTE plot, videos); left turn: each agent's first episode
    as a video."""
    env_name, out_dir = env_cfg["name"], command.out_dir
    if env_name == "lane_keeping" and (command.plots or command.videos):
        from eval.plots import lane_keeping_figures

        paths = lane_keeping_figures(env_cfg, plans, out_dir, first_seed, command.paths.checkpoints, command.split,
                                     command.plots, command.videos)
        print(f"[eval] figures (seed {first_seed}): {', '.join(p.name for p in paths)}")
    if env_name == "left_turn" and command.videos:
        from eval.plots import turn_videos

        paths = turn_videos(env_cfg, plans, out_dir, first_seed, command.paths.checkpoints)
        print(f"[eval] videos (seed {first_seed}): {', '.join(p.name for p in paths)}")


def results_problem(command: EvalCommand) -> str | None:
    """An ``out_dir`` inside the shipped references, or holding a meta.json that eval did not write, is refused;
    one that holds an evaluation's results is not written over unless ``overwrite=true``. The default out_dir,
    Hydra's job folder, was judged so by Hydra's hooks before Hydra made it (eval/job_folders.py: the same rule)."""
    from eval.job_folders import outputs_problem

    return outputs_problem(command.out_dir, command.overwrite, "out_dir",
                           elsewhere=" (or leave it out: a new folder under runs/eval/)")


def _check_command_line() -> None:
    """The command line composed and checked once per config (conf/check.py), its out_dir too; for a plain run
    the out_dir claimed: all before Hydra makes a folder."""
    from conf.check import _PLACEHOLDER, check_command_line

    commands = []

    def check(cfg: DictConfig) -> None:  # its fields were checked by check_command_line
        command = _check_needs(cfg)
        if command.out_dir != _PLACEHOLDER:  # the default, Hydra's run folder, was checked with hydra.run.dir
            problem = folder_problem(command.out_dir, "out_dir") or results_problem(command)
            if problem:
                raise ConfigError(problem)
        commands.append(command)

    configs = check_command_line("eval", sys.argv[1:], check)
    sweep = len(configs) != 1 or any(a in ("-m", "--multirun") for a in sys.argv[1:])
    command = None if sweep else commands[0]
    if command is not None and command.out_dir != _PLACEHOLDER:
        # before Hydra makes its run folder: an out_dir another evaluation is writing is refused with nothing
        # written; the lock is held by this process until the evaluation ends (a sweep's jobs each lock their own)
        claim_out_dir(command)


@hydra.main(config_path="pkg://conf", config_name="eval", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    from conf.run_log import job_logged

    run_cli(job_logged(evaluate), cfg, hydra_run_dir=True)  # the run folder's __main__.log holds what it prints


def main() -> None:
    """Check the command line before Hydra makes a run folder (one line and exit 2 on bad input), then run."""
    from conf.hydra_files import hydra_files_whole

    run_cli(_check_command_line)
    with hydra_files_whole():  # Hydra's .hydra/*.yaml written whole, or one line and no run folder left
        run_hydra(_hydra_main)  # a sweep runs every job, then reports the failed ones


if __name__ == "__main__":
    main()
