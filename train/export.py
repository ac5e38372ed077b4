"""Export a trained run as a reference checkpoint: ``python -m train.export checkpoints/<run>
checkpoints/<name> [--best] [--command "python -m train ..."] [--overwrite] [--overwrite-reference]``.

Writes the run's model file (its agent kind's ``checkpoint``), the run's ``config.yaml`` beside it, and ``COMMAND``
(the command that trained it; every reference folder has one, ``tests/test_reference_checkpoints.py``). An SB3 run
(PPO, DAgger) gives ``<dest>/model.zip`` (the run's ``model.zip``, or ``best.zip`` with ``--best``) without the
optimizer's state. Why drop the optimizer: Adam keeps two moments per weight, two thirds of an SB3 zip; a reference
checkpoint is for ``python -m eval``, which never steps an optimizer (resuming training reads the run's own folder).
The policy's weights, and so its actions, are unchanged. A PilotNet run gives ``<dest>/model.pt`` byte for byte
(checked to load first): it holds the best validation epoch's weights and no optimizer, so there is nothing to drop
and no ``best.zip`` to choose.

The shipped reference agents (``checkpoints/reference/``, :func:`av_gym.references.reference_root`) are read-only
to the tools (an export of a lane keeper replaced the shipped ``ppo_turn``): a destination there is
refused unless ``--overwrite-reference`` is given, and then only for a checkpoint of the same scenario, actions,
kind and sensors as the reference it replaces, with ``--command``; the folder's model, config and COMMAND are
replaced in one step (:func:`av_gym.atomic.replace_folder_atomic`).

Any other destination is held while it is written (its ``.lock``, the lock a training run holds: a run in progress
is refused) and must be empty or new: a folder holding files (another run's model, an earlier export) is replaced,
all of its files, only with ``--overwrite``."""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

from av_gym.atomic import LOCK, OwnedFolders
from av_gym.errors import ConfigError, run_cli
from conf.cli import ToolParser, out_folder_problem

# What a reference's name promises: ``eval agents=[ppo_turn]`` runs whatever ``reference/ppo_turn`` holds, on the
# scenario, actions and sensors its config.yaml says. A replacement must keep them, or the name (and every table
# labelled with it) would silently mean another agent.
SAME_AS_REFERENCE = ("env.name", "env.action", "agent.kind", "agent.actions", "sensors.name")
FLAG = "--overwrite-reference"
OVERWRITE = "--overwrite"
DESTS = OwnedFolders()  # the folders this process writes a checkpoint into (the lock a training run takes too)


def _get(cfg: Mapping, dotted: str):
    node = cfg
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, Mapping) else None
    if dotted == "agent.actions" and node is None:
        return "env"  # PPOParams' default: the env's own action space
    return node


def reference_problem(dest: Path, new_cfg: Mapping, overwrite_reference: bool, has_command: bool,
                      tool: str) -> str | None:
    """Why ``tool`` may not write a checkpoint with config ``new_cfg`` into ``dest``, or None. Only a folder under
    the shipped references is guarded; there, the flag, a checkpoint like the one it replaces and its command."""
    from av_gym.references import is_shipped, reference_root

    if not is_shipped(dest):
        return None
    root = reference_root()
    if dest.resolve() == root.resolve():
        return (f"{tool}: {dest} is the folder of every shipped reference agent; give one agent's folder "
                f"({dest}/<name>)")
    name = dest.resolve().relative_to(root.resolve())
    if not overwrite_reference:
        return (f"{tool}: {dest} is the shipped reference agent {str(name)!r} (checkpoints/reference/ is read-only "
                f"to the tools); write elsewhere (e.g. checkpoints/<name>), or pass {FLAG} to replace it with a "
                f"checkpoint of the same scenario, actions and sensors")
    from agents.checkpoint import read_config_yaml

    old = read_config_yaml(dest / "config.yaml")
    if old:
        for key in SAME_AS_REFERENCE:
            if _get(old, key) != _get(new_cfg, key):
                return (f"{tool} {FLAG}: {dest} holds {str(name)!r} with {key}={_get(old, key)}, this checkpoint "
                        f"has {key}={_get(new_cfg, key)}; a reference is replaced only by a checkpoint with the same "
                        f"{', '.join(SAME_AS_REFERENCE)}")
    if not has_command:
        return (f"{tool} {FLAG}: give the command that made the new checkpoint (--command \"python -m train ...\"): "
                f"{dest}/COMMAND must say how its model was made, not how the one it replaces was")
    return None


def lookalike_note(dest: Path) -> str | None:
    """A note when ``dest`` looks like a reference's folder (``.../checkpoints/reference/<agent>``, in a project
    of yours) but is not inside the shipped references: written as any folder (it is yours), but a named agent
    (``agents=[pilotnet]``) always means the shipped reference, so this checkpoint is evaluated by its path."""
    from av_gym.references import is_shipped, reference_root

    parts = dest.resolve().parts[:-1]
    if is_shipped(dest) or not any(parts[i:i + 2] == ("checkpoints", "reference") for i in range(len(parts))):
        return None
    return (f"{dest} is not a shipped reference ({reference_root()}/...): named agents (agents=[{dest.name}]) do "
            f"not read it; evaluate it by its path, agents=[{dest}], its rows labelled so")


def write_checkpoint_folder(dest: Path, files: dict[str, Callable[[Path], object] | str],
                            keep_others: bool = True) -> Path:
    """Write ``files`` (name → text, or a function writing that file's path) into ``dest``, all of them replacing
    the folder's at once: built in a hidden sibling, then swapped in (a crash or a full disk leaves the old folder
    whole). Files of ``dest`` not in ``files`` are carried over (``keep_others``): nothing of the old folder is
    lost but what is replaced."""
    from av_gym.atomic import replace_folder_atomic

    def fill(tmp: Path) -> None:
        if (dest / LOCK).is_file():  # the same lock file (a hard link): the swapped-in folder stays ours alone
            (tmp / LOCK).hardlink_to(dest / LOCK)
        if keep_others and dest.is_dir():
            for p in dest.iterdir():
                if p.name not in files and p.name != LOCK:
                    (shutil.copytree if p.is_dir() else shutil.copy2)(p, tmp / p.name)
        for name, content in files.items():
            if isinstance(content, str):
                (tmp / name).write_text(content)
            else:
                content(tmp / name)

    return replace_folder_atomic(dest, fill, "dest")


def dest_problem(run_dir: Path, dest: Path, overwrite: bool) -> str | None:
    """Why ``dest`` (a folder not inside the shipped references) may not receive ``run_dir``'s checkpoint, or None:
    it holds the shipped references or other folders (``checkpoints/``), it cannot be written, it is the run's own
    folder, or it holds files (another run's, an earlier export) and ``overwrite`` was not given."""
    problem = out_folder_problem(dest, "dest", cleared=True)
    if problem:
        return problem
    if dest.resolve() == run_dir.resolve():
        return f"dest={dest} is run_dir itself; write the checkpoint elsewhere (e.g. {dest}-export)"
    held = sorted(p.name for p in dest.iterdir() if p.name != LOCK) if dest.is_dir() else []
    folders = [name for name in held if (dest / name).is_dir()]
    if folders:  # checkpoints/, say: --overwrite would replace every run in it
        return (f"dest={dest} holds folders ({', '.join(folders[:3])}{' ...' if len(folders) > 3 else ''}), so it is "
                f"not one checkpoint's folder; give the folder of one checkpoint, e.g. {dest}/<name>")
    if held and not overwrite:
        return (f"dest={dest} already holds {', '.join(held[:3])}{' ...' if len(held) > 3 else ''} (another run's "
                f"or an earlier export); write elsewhere, or replace its files with {OVERWRITE}")
    return None


@contextlib.contextmanager
def destination(run_dir: Path, dest: Path, cfg: Mapping, tool: str, overwrite: bool = False,
                overwrite_reference: bool = False, has_command: bool = False) -> Iterator[bool]:
    """``dest`` checked (:func:`reference_problem`, :func:`dest_problem`) and held for this process while the
    block writes it (the lock a training run holds, so a run in progress is refused, and checked again under it);
    yields whether the folder's other files are carried over (a shipped reference's) or all replaced."""
    from av_gym.references import is_shipped

    if not str(dest).strip() or dest.name in ("", ".", ".."):
        raise ConfigError(f"{tool}: dest={str(dest)!r}: give the folder to write, e.g. checkpoints/<name>")
    problem, shipped = reference_problem(dest, cfg, overwrite_reference, has_command, tool), is_shipped(dest)
    if not problem and not shipped:
        problem = dest_problem(run_dir, dest, overwrite)
    if problem:
        raise ConfigError(problem)
    DESTS.claim(dest, "dest")  # a training run's, or another export's
    try:
        problem = None if shipped else dest_problem(run_dir, dest, overwrite)  # written while we waited?
        if problem:
            raise ConfigError(problem)
        yield shipped
    finally:
        DESTS.release(dest)


def export_reference(run_dir: str | Path, dest: str | Path, best: bool = False, command: str | None = None,
                     overwrite_reference: bool = False, overwrite: bool = False) -> Path:
    """Copy run ``run_dir``'s policy (``model.zip`` or ``best.zip``) and ``config.yaml`` to ``dest``, and write
    ``command`` to ``dest/COMMAND`` if given; returns the written zip. The folder's files are replaced at once,
    under its lock: a folder holding files only with ``overwrite`` (:func:`dest_problem`), a shipped reference
    only as :func:`reference_problem` allows."""
    from agents.checkpoint import read_config_yaml

    run_dir, dest = Path(run_dir), Path(dest)
    cfg = read_config_yaml(run_dir / "config.yaml")
    name = _model_file(cfg, best)
    src = run_dir / ("best.zip" if best else name)
    for path in (src, run_dir / "config.yaml"):
        if not path.is_file():
            raise ConfigError(f"{path} does not exist: run_dir must be a training run's checkpoint folder "
                              f"(checkpoints/<run_name>/ with {name}{', best.zip' if best else ''} and config.yaml)")
    with destination(run_dir, dest, cfg, "python -m train.export", overwrite, overwrite_reference,
                     bool(command)) as keep_others:
        files: dict = {name: (_sb3_writer if name == "model.zip" else _torch_writer)(src),
                       "config.yaml": portable_config((run_dir / "config.yaml").read_text())}
        if command:
            files["COMMAND"] = command.rstrip("\n") + "\n"
        write_checkpoint_folder(dest, files, keep_others)
    return dest / name


def portable_config(text: str) -> str:
    """A run's ``config.yaml`` text as an export writes it. Training writes the resolved config, so a preset's
    ``agent.init_from: ${av_gym_reference:dagger_turn}`` (conf/agent/dagger_turn_perceived.yaml) is recorded as this
    install's absolute path (the checkout's, or site-packages'), a path no other machine has: an ``init_from``
    inside the shipped references (:func:`av_gym.references.is_shipped`) is written back as that interpolation,
    which every install resolves to its own copy (conf/__init__.py). Any other text is kept byte for byte."""
    import yaml
    from omegaconf import OmegaConf

    from av_gym.references import is_shipped, reference_root

    cfg = yaml.safe_load(text)
    agent = cfg.get("agent") if isinstance(cfg, dict) else None
    init_from = agent.get("init_from") if isinstance(agent, dict) else None
    if not isinstance(init_from, str) or "${" in init_from or not is_shipped(init_from):
        return text
    name = Path(init_from).resolve().relative_to(reference_root().resolve()).as_posix()
    if name == ".":
        return text
    agent["init_from"] = f"${{av_gym_reference:{name}}}"
    return OmegaConf.to_yaml(OmegaConf.create(cfg))  # the writer training used (train/__main__.py): same layout


def _model_file(cfg: Mapping, best: bool) -> str:
    """The model file a run of ``cfg``'s agent kind holds (``model.zip`` when the config names no known kind: the
    SB3 runs this tool was first written for). ``best`` only for SB3 runs, which keep ``best.zip`` beside it."""
    from agents.registry import AGENT_KINDS

    kind = _get(cfg, "agent.kind")
    name = (AGENT_KINDS.get(kind).checkpoint if kind in AGENT_KINDS else None) or "model.zip"
    if best and name != "model.zip":
        raise ConfigError(f"--best: a run of agent.kind={kind} keeps one {name}, already its best validation epoch "
                          f"(there is no best.zip); export it without --best")
    return name


def _sb3_writer(src: Path) -> Callable[[Path], object]:
    """Writes ``src``'s SB3 model without the optimizer's moments (one line for an empty, truncated or corrupt
    zip, raised now, before the destination is touched)."""
    from agents.checkpoint import load_sb3

    model = load_sb3(src, device="cpu")
    policy = model.policy
    policy.optimizer = policy.optimizer_class(policy.parameters(), lr=model.lr_schedule(1.0),
                                              **policy.optimizer_kwargs)  # fresh: no moments
    return lambda p: model.save(str(p))


def _torch_writer(src: Path) -> Callable[[Path], object]:
    """Copies ``src`` (PilotNet's ``model.pt``: weights and plain values, no optimizer) byte for byte, once it has
    loaded as the kind's checkpoint (one line naming the file when it does not)."""
    from agents.pilotnet import load_policy

    try:
        load_policy(src)  # weights_only=True: the shapes and format checked as eval will load them
    except (ValueError, RuntimeError, EOFError, OSError, KeyError) as exc:
        raise ConfigError(f"{src}: {(str(exc).splitlines() or [type(exc).__name__])[0]}") from None
    return lambda p: shutil.copyfile(src, p)


def main(argv: list[str] | None = None) -> None:
    parser = ToolParser(prog="python -m train.export", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="checkpoints/<run_name>/ of a training run (PPO, DAgger: model.zip; "
                                        "PilotNet: model.pt)")
    parser.add_argument("dest", help="folder to write, e.g. checkpoints/<name> (the shipped "
                                     f"checkpoints/reference/<agent>: only with {FLAG})")
    parser.add_argument("--best", action="store_true", help="export best.zip (the best periodic evaluation; SB3 "
                                                            "runs)")
    parser.add_argument("--command", help="the command that trained the run, written to DEST/COMMAND")
    parser.add_argument(FLAG, action="store_true",
                        help="allow DEST to be a shipped reference agent's folder: replaced (model, config and "
                             "COMMAND at once) by a checkpoint of the same scenario, actions, kind and sensors; "
                             "needs --command")
    parser.add_argument(OVERWRITE, action="store_true",
                        help="allow DEST to hold files (an earlier export, another run's): all of them replaced")
    args = parser.parse_args(argv)
    out = export_reference(args.run_dir, args.dest, args.best, args.command, args.overwrite_reference,
                           args.overwrite)
    print(f"[export] {out} ({out.stat().st_size / 1e6:.1f} MB) and config.yaml")
    note = lookalike_note(Path(args.dest))
    if note:
        print(f"[export] note: {note}")
    if not (out.parent / "COMMAND").is_file():
        print(f"[export] {out.parent}/COMMAND is missing: write the command that trained the run there "
              f"(--command), as every reference checkpoint has")


if __name__ == "__main__":
    run_cli(main)
