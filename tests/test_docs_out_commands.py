"""A documented command of a tool that refuses to replace its output (``--out`` or ``--rows`` already there: the
ccftap / tracking / interventions / tradeoff tools without ``--overwrite``, batched_speed, soak, belief_planner,
label_noise, the belief_tracks benchmarks, eval.curves) does not name a shipped path without ``--overwrite``: typed as
written it would only be refused (closing note of 2026-11-30: docs/shield.md's ccftap and docs/performance.md's
batched_speed history commands). Fenced commands and inline ones in the prose alike, in README.md and docs/*.md; not
in the result folders' pages (docs/ccftap/results.md, docs/tracking/tracking.md ...), a tool's own record of the
command line it ran, which is part of the measured result and stays as written."""

from __future__ import annotations

import re
import shlex

from documented_commands import ROOT, all_blocks, documents

REFUSING = {"eval.ccftap", "eval.tracking", "eval.interventions", "eval.tradeoff", "eval.curves",
            "benchmarks/batched_speed.py", "benchmarks/soak.py", "benchmarks/belief_planner.py",
            "benchmarks/label_noise.py", "benchmarks/belief_tracks_ablate.py", "benchmarks/belief_tracks_paired.py",
            "benchmarks/belief_tracks_sweep.py"}
OUTPUT_FLAGS = ("--out", "--rows")


def _inline_commands() -> list[tuple[str, str]]:
    """(document, command) of every inline code span of the documents that starts with ``python``."""
    found = []
    for path in documents():
        if not _written_by_hand(str(path.relative_to(ROOT))):
            continue
        text = re.sub(r"^```.*?^```", "", path.read_text(), flags=re.S | re.M)  # the fenced blocks: all_blocks
        for m in re.finditer(r"`(python [^`]+)`", text):  # from its own backtick: an odd one earlier cannot pair
            found.append((str(path.relative_to(ROOT)), " ".join(m.group(1).split())))
    return found


def _written_by_hand(doc: str) -> bool:
    """README.md and docs/*.md, not a page a tool wrote into a result folder (docs/<folder>/...)."""
    return doc.count("/") <= 1


def refused_as_written(command: str) -> str | None:
    """The shipped output ``command`` names without ``--overwrite``, if it is a refusing tool's; else None."""
    try:
        argv = shlex.split(command)
    except ValueError:
        return None
    tool = argv[2] if len(argv) > 2 and argv[1] == "-m" else argv[1] if len(argv) > 1 else ""
    if tool not in REFUSING or "--overwrite" in argv:
        return None
    for flag, value in zip(argv, argv[1:]):
        if flag in OUTPUT_FLAGS and (ROOT / value).exists():
            return f"{flag} {value}"
    return None


def test_the_check_sees_a_refused_history_command():
    assert refused_as_written("python -m eval.ccftap --variants improved --out docs/ccftap") == "--out docs/ccftap"
    assert refused_as_written("python -m eval.ccftap --out docs/ccftap --overwrite") is None
    assert refused_as_written("python benchmarks/batched_speed.py --out docs/batched_speed.png") == \
        "--out docs/batched_speed.png"
    assert refused_as_written("python benchmarks/batched_speed.py --out runs/new_speed.png") is None


def test_no_documented_command_names_a_shipped_output_it_would_refuse():
    commands = [(c.doc, c.text) for block in all_blocks() for c in block if _written_by_hand(c.doc)]
    commands += _inline_commands()
    bad = [f"{doc}: {text[:100]} ({out} exists; add --overwrite or a fresh path)"
           for doc, text in commands if (out := refused_as_written(text))]
    assert bad == []
