"""The documents say what is true now and point at what exists: every link and image of README.md and
docs/**/*.md resolves to a file, every ``docs/...`` path a page or the code names exists, docs/ stays small (one
current page per topic, the figures and data those pages show), and no page, comment, docstring or config comment
narrates the project's history by issue, round, pass, session or issue-table row numbers (that history is git's; a
page may name a commit: ``git show <commit>:docs/...`` is not a path of the tree and is not checked)."""

from __future__ import annotations

import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
MAX_DOCS_FILES = 30  # pages, their figures and scripts: everything under docs/ but the result folders
MAX_RESULT_FOLDERS = 31  # docs/results/<name>/: measured data, each exactly results.csv + meta.json (the results page);
# a preset changed under one agent name (belief_tracks: left_turn_sensing_mended, _wait) needs a folder per look
CODE_DIRS = ("av_gym", "agents", "train", "eval", "conf", "benchmarks", "tests", "docs")

# Narration: a number that only means something in the project's tracker or its work log. DAgger's own numbered
# rounds (its iterations: "round 0", "interrupted in round N") and words such as "round trip" or "passes 1.5x" are not
# narration; a round of work is written "round N's", "round-N", "round N seed/recipe/table/...".
NARRATION = re.compile(
    r"\b(?:issues?|sessions?)[ -]#?\d+"                                          # the tracker, the work log
    r"|\bround-[1-9]|\bround [1-9]\d*(?:'s\b|(?= (?:seed|recipe|polic|table|budget|reference|session|below|above"
    r"|shield|(?:and|or) [1-9])))"                                              # a numbered round of work
    r"|\bpass \d+\b"
    r"|\b(?:second|third|fourth|fifth|sixth|2nd|3rd|4th|5th)[ -](?:pass|round|session)\b"
    r"|\bfirst[ -](?:pass|session)\b"
    r"|\brows? \d+(?:(?:, | and |-)\d+)*[:)]",                                    # a row of an issue's table
    re.IGNORECASE)

LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_LINK = re.compile(r"^\s*\[[^\]]+\]:\s*(\S+)", re.MULTILINE)
HTML_SRC = re.compile(r"""<(?:img|a)\b[^>]*?\b(?:src|href)=["']([^"']+)["']""", re.IGNORECASE)
DOCS_PATH = re.compile(r"(?<![\w/.\-])docs/[\w.*/<>{},\-]*")
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def code_files() -> list[Path]:
    dirs = [ROOT / d for d in CODE_DIRS]
    dirs += [p for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").is_file() and p not in dirs]
    return sorted(f for d in dirs if d.is_dir() for f in d.rglob("*.py") if "__pycache__" not in f.parts)


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


# ------------------------------------------------------------------------------------------------ links and paths
def link_targets(text: str) -> list[str]:
    """The local targets of a page's links and images (outside code), without their #anchor."""
    prose = INLINE_CODE.sub("", FENCE.sub("", text))
    found = [*LINK.findall(prose), *REFERENCE_LINK.findall(prose), *HTML_SRC.findall(prose)]
    return [t.split("#", 1)[0] for t in found if t.split("#", 1)[0] and not re.match(r"[a-z][a-z0-9+.-]*:", t)]


def docs_paths(text: str) -> list[str]:
    """Every ``docs/...`` path named in ``text`` (code included), but not ``<commit>:docs/...`` (a git object)."""
    found = []
    for m in DOCS_PATH.finditer(text):
        if m.start() > 0 and text[m.start() - 1] == ":":
            continue
        path = m.group(0).rstrip(".,;:")
        if path != "docs/":
            found.append(path)
    return found


def _expand(path: str) -> list[str]:
    """``a{b,c}d`` -> ``abd``, ``acd`` (one level, as the pages write it)."""
    m = re.search(r"\{([^{}]*)\}", path)
    if not m:
        return [path]
    return [p for alt in m.group(1).split(",") for p in _expand(path[:m.start()] + alt + path[m.end():])]


def exists(path: str) -> bool:
    """Whether a named path exists: a ``<placeholder>`` needs what comes before it, a glob a match."""
    for one in _expand(path):
        if "<" in one:
            one = one[:one.index("<")].rsplit("/", 1)[0] or "."
        if any(c in one for c in "*?["):
            if not any(True for _ in ROOT.glob(one)):
                return False
        elif not (ROOT / one).exists():
            return False
    return True


def broken_links() -> list[str]:
    out = []
    for page in pages():
        for target in link_targets(page.read_text()):
            if not (page.parent / target).exists():
                out.append(f"{_rel(page)}: link or image {target!r} does not exist")
    return out


def missing_docs_paths() -> list[str]:
    out = []
    for f in [*pages(), *code_files()]:
        for i, line in enumerate(f.read_text().splitlines(), 1):
            out += [f"{_rel(f)}:{i}: {p}" for p in docs_paths(line) if not exists(p)]
    return out


# A path into the code or the shipped data that a page names (prose, inline code or a code block), e.g.
# ``conf/sensors/detector.yaml``, ``av_gym/estimation/ekf.py``, ``checkpoints/reference/pilotnet``; ``docs/...`` is
# :func:`docs_paths`'s. Not a path: a Gymnasium id (``av_gym/LaneKeepingLap-v0``).
REPO_PATH = re.compile(r"(?<![\w/.\-:$])(?:conf|av_gym|av_gym_harness|av_gym_sb3|agents|train|eval|benchmarks|tests"
                       r"|checkpoints/reference|\.ci)/[\w.*/<>{},\-]*")
GYM_ID = re.compile(r"-v\d+$")
WHEEL_ONLY = ("av_gym/_shipped/",)  # what setup.py copies into a wheel: in no checkout (docs/design.md, Packaging)


def repo_paths(text: str) -> list[str]:
    """Every path into the code or shipped data named in ``text``; ``a,b`` lists split (``{a,b}`` is one path)."""
    found = []
    for m in REPO_PATH.finditer(text):
        for path in re.split(r",(?![^{]*})", m.group(0)):
            path = path.rstrip(".,;:")
            if path.count("/") and not GYM_ID.search(path) and not path.startswith(WHEEL_ONLY):
                found.append(path)
    return found


def missing_repo_paths() -> list[str]:
    return [f"{_rel(page)}:{i}: {p}" for page in pages() for i, line in enumerate(page.read_text().splitlines(), 1)
            for p in repo_paths(line) if not exists(p)]


PYTHON_M = re.compile(r"\bpython3? -m ([A-Za-z_][\w.]*)")


def missing_modules() -> list[str]:
    """``python -m <module>`` in a page whose module is neither a file of the checkout nor installed."""
    import importlib.util

    out = []
    for page in pages():
        for i, line in enumerate(page.read_text().splitlines(), 1):
            for module in PYTHON_M.findall(line):
                path = ROOT / module.replace(".", "/")
                if not (path.with_suffix(".py").is_file() or (path / "__main__.py").is_file()
                        or importlib.util.find_spec(module.split(".")[0]) is not None and "." not in module):
                    out.append(f"{_rel(page)}:{i}: python -m {module}")
    return out


def docs_files() -> list[Path]:
    return sorted(p for p in DOCS.rglob("*") if p.is_file() and "__pycache__" not in p.parts
                  and not p.name.startswith("."))


# ------------------------------------------------------------------------------------------------ narration
def _comments_and_strings(source: str):
    """(line, text) of every comment and string literal (docstrings included) of a Python source."""
    middle = getattr(tokenize, "FSTRING_MIDDLE", None)
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type in (tokenize.COMMENT, tokenize.STRING) or (middle is not None and tok.type == middle):
            for k, text in enumerate(tok.string.splitlines()):
                yield tok.start[0] + k, text


def narration() -> list[str]:
    """Every narrating line: README.md and docs/ pages, comments and strings of the code, conf/ yaml files."""
    out = []
    for page in pages():
        out += [f"{_rel(page)}:{i}: {line.strip()}" for i, line in enumerate(page.read_text().splitlines(), 1)
                if NARRATION.search(line)]
    for f in code_files():
        seen = set()
        for i, text in _comments_and_strings(f.read_text()):
            if NARRATION.search(text) and i not in seen:
                seen.add(i)
                out.append(f"{_rel(f)}:{i}: {text.strip()}")
    for f in sorted((ROOT / "conf").rglob("*.yaml")):
        out += [f"{_rel(f)}:{i}: {line.strip()}" for i, line in enumerate(f.read_text().splitlines(), 1)
                if NARRATION.search(line)]
    return out


# ------------------------------------------------------------------------------------------------ the tests
def test_every_link_and_image_of_the_pages_resolves():
    broken = broken_links()
    assert not broken, "\n".join(broken)


def test_every_docs_path_the_pages_and_the_code_name_exists():
    missing = missing_docs_paths()
    assert not missing, "paths under docs/ that do not exist:\n" + "\n".join(missing)


def test_every_code_or_shipped_path_the_pages_name_exists():
    missing = missing_repo_paths()
    assert not missing, "paths the pages name that do not exist:\n" + "\n".join(missing)


def test_every_module_the_pages_run_exists():
    missing = missing_modules()
    assert not missing, "python -m <module> lines whose module does not exist:\n" + "\n".join(missing)
    assert PYTHON_M.findall("`python -m eval.sweep <folder>`, python3 -m venv .venv") == ["eval.sweep", "venv"]


def test_the_repo_path_checker():
    gone = "conf/" + "sensor/detector.yaml"  # written in two parts, or this file would name a missing path itself
    assert repo_paths(f"defaults of {gone}: 60 m") == [gone] and not exists(gone)
    assert repo_paths("`gym.make(\"av_gym/LaneKeepingLap-v0\")` and train/bc.py: augment") == ["train/bc.py"]
    assert repo_paths("agents=[checkpoints/reference/seeds/a/s1,checkpoints/reference/seeds/a/s3]") == \
        ["checkpoints/reference/seeds/a/s1", "checkpoints/reference/seeds/a/s3"]
    assert repo_paths("`conf/{train,eval}.yaml`") == ["conf/{train,eval}.yaml"] and exists("conf/{train,eval}.yaml")
    assert exists("checkpoints/reference/seeds/ppo_turn/s<S>")


def test_docs_holds_one_page_per_topic_and_what_those_pages_show():
    results = DOCS / "results"
    pages = [p for p in docs_files() if results not in p.parents]
    assert len(pages) <= MAX_DOCS_FILES, (f"{len(pages)} files under docs/ outside docs/results/ (at most "
                                          f"{MAX_DOCS_FILES}): merge pages, leave superseded data to git")
    folders = sorted(p for p in results.iterdir() if p.is_dir())
    assert len(folders) <= MAX_RESULT_FOLDERS, (f"{len(folders)} result folders (at most {MAX_RESULT_FOLDERS}): "
                                                f"measure rows that belong together in one folder")
    loose = [str(p) for p in docs_files() if results in p.parents
             and (p.parent.parent != results or p.name not in ("results.csv", "meta.json"))]
    assert not loose, f"a result folder holds results.csv and meta.json only: {loose}"


def test_no_document_comment_or_docstring_narrates_the_history():
    found = narration()
    assert not found, ("say what is true now (history is git's; a page may name a commit):\n" + "\n".join(found))


@pytest.mark.parametrize("text, hit", [
    ("a round trip", False), ("DAgger's round 0: the teacher drives", False), ("stops once the KL passes 1.5x", False),
    ("row 12.5, hence crop_top", False), ("rows 32+: no duplicates", False), ("the first round of DAgger", False),
    ("interrupted in round 2: rounds 0..1 are kept", False), ("round" + " 2 seed 1", True),
    ("the " + "issue" + " 17 shield", True), ("(" + "issue" + " 31 " + "row" + " 15)", True), ("round" + " 3's table", True),
    ("third" + " pass", True), ("session" + " 27", True), ("Row" + " 4: run_name", True), ("round" + "-2 recipe", True),
])
def test_the_narration_pattern(text, hit):
    assert bool(NARRATION.search(text)) is hit


def test_the_path_checker_reads_globs_placeholders_and_git_objects():
    assert docs_paths("`git show 3f8976e:docs/gone/x.md` and docs/results.md.") == ["docs/results.md"]
    assert exists("docs/results/left_turn_*/results.csv") and exists("docs/results/<name>/results.csv")
    gone = "no_such_page.md"  # written in two parts, or this file would name a missing path itself
    assert not exists("docs/" + gone) and not exists("docs/" + "{results.md," + gone + "}")
    assert link_targets("![x](a.png) [y](https://e.org) [z](#top) `[q](not_a_link.md)` [r](b.md#part)") == \
        ["a.png", "b.md"]
