"""The project's files speak of the project: no chronicle of numbered rounds of work.

Every tracked text file (README, docs, the model card, config descriptions, docstrings, comments, test
names) is scanned for wording that narrates the project's own history by number: a numbered work period
(the words of :data:`WORDS` followed by a number), "part N of", or a count of past periods. A figure is dated
by its commit (docs/benchmarks.md), a rule is described by what it does. The check fails listing file:line.
This file scans itself too: its examples are built from parts (:func:`narrate`).
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".txt", ".json", ".cfg", ".sh", ".mjs", ".js"}
NOT_SCANNED = {"viewer/package-lock.json"}  # npm's data
SKIPPED_DIRS = {".git", ".venv", "node_modules", "ms3d-work", "__pycache__", ".ms3d-cache"}
MAX_BYTES = 2_000_000  # larger tracked files are data, not prose
WORDS = ("ses" + "sion", "st" + "op", "ro" + "und", "is" + "sue")  # a work period, when a number follows
_W = "|".join(WORDS)
CHRONICLE = re.compile(
    rf"\b(?:{_W})s?[\ -]\#?\d+\b"                                         # the word, then a number
    rf"|\b{WORDS[0]}s?\ ago\b"                                            # N of them ago
    rf"|\b(?:this|that|earlier|previous|last|next|later)\ {WORDS[0]}s?\b"  # the one before
    r"|\bpart\ \d+\ of\b",                                                # one of several parts
    re.IGNORECASE | re.VERBOSE,
)


def narrate(word: int, text: str) -> str:
    """``text`` with ``{}`` replaced by ``WORDS[word]``: an example line built from parts."""
    return text.format(WORDS[word])


def chronicle_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line of ``text`` that narrates a numbered round of work.

    >>> chronicle_lines(narrate(2, "kept as measured in {} 20") + "\\nthe repair keeps unseen faces\\n")[0][0]
    1
    >>> chronicle_lines("the repair keeps unseen faces\\n")
    []
    """
    return [(i, line.strip()) for i, line in enumerate(text.splitlines(), 1) if CHRONICLE.search(line)]


def tracked_text_files() -> list[Path]:
    """The text files git tracks; outside a git checkout, every text file of the tree but the build and
    work folders (so the check never silently scans nothing)."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
        names = [n for n in out.decode().split("\0") if n]
    except (OSError, subprocess.CalledProcessError):
        names = [p.relative_to(ROOT).as_posix() for p in ROOT.rglob("*")
                 if not SKIPPED_DIRS & set(p.relative_to(ROOT).parts)]
    return [ROOT / n for n in names if n not in NOT_SCANNED and (ROOT / n).suffix in TEXT_SUFFIXES
            and (ROOT / n).is_file() and (ROOT / n).stat().st_size <= MAX_BYTES]


def test_the_check_finds_a_chronicle_and_passes_a_clean_line():
    line = narrate(0, "measured in {} 20")
    assert chronicle_lines(line) == [(1, line)]
    for word, narrated in ((1, "a full disk failed CI at {} 34"), (3, "see {} 14, item 2"), (3, "({} #9)"),
                           (0, "figures of earlier {}s"), (0, "the {}-18 code"), (2, "changed in {} 3"),
                           (0, "as stated 3 {}s ago")):
        assert chronicle_lines(narrate(word, narrated)), narrated
    assert chronicle_lines("part " + "2 of the review")
    for clean in ("the repair keeps unseen faces (repair.mesh.keep_unseen_m, 0.5 m)",
                  narrate(0, "the {}'s moto S3 server on 127.0.0.1"), narrate(0, "one Prefect server per test {}"),
                  "AWS_SESSION_TOKEN", "round(x, 3) to 3 decimals", "workers stop within 8 s"):
        assert not chronicle_lines(clean), clean


def test_no_tracked_file_narrates_numbered_rounds_of_work():
    files = tracked_text_files()
    assert any(p.name == "README.md" for p in files) and any(p.name == "test_no_chronicle.py" for p in files)
    found = []
    for path in files:
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue  # binary data under a text suffix
        found += [f"{path.relative_to(ROOT)}:{i}: {line[:120]}" for i, line in chronicle_lines(text)]
    assert not found, "chronicle wording (describe the code, date a figure by its commit):\n" + "\n".join(found)
