"""The project's files speak of the project: no chronicle of numbered rounds of work.

Every tracked text file (README, docs, the model card, config descriptions, docstrings, comments, test
names) is scanned for wording that narrates the project's own history by number ("measured in session 20",
"a full disk failed CI at stop 34", "issue 14, part 2 of 3", "earlier sessions"). A figure is dated by its
commit (docs/benchmarks.md), a rule is described by what it does. The check fails listing file:line.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".txt", ".json", ".cfg", ".sh", ".mjs", ".js"}
NOT_SCANNED = {
    "tests/test_no_chronicle.py",  # this file names the patterns
    "viewer/package-lock.json",    # npm's data
}
MAX_BYTES = 2_000_000  # larger tracked files are data, not prose

CHRONICLE = re.compile(
    r"""
      \bsessions?[\ -]\d+\b                                   # session 20, session-18 code
    | \bsessions?\ ago\b
    | \b(?:this|that|earlier|previous|last|next|later)\ sessions?\b
    | \bstops?\ \d+\b                                         # stop 34
    | \brounds?\ \d+\b                                        # round 3
    | \bissues?\ \#?\d+\b                                     # issue 14, issue #14
    | \bpart\ \d+\ of\b                                       # part 2 of 3
    """,
    re.IGNORECASE | re.VERBOSE,
)


def chronicle_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line of ``text`` that narrates a numbered round of work.

    >>> chronicle_lines("kept as measured in session 20\\nthe repair keeps unseen faces\\n")
    [(1, 'kept as measured in session 20')]
    """
    return [(i, line.strip()) for i, line in enumerate(text.splitlines(), 1) if CHRONICLE.search(line)]


def tracked_text_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: the tracked files are unknown")
    files = []
    for name in out.decode().split("\0"):
        path = ROOT / name
        if (name and name not in NOT_SCANNED and path.suffix in TEXT_SUFFIXES and path.is_file()
                and path.stat().st_size <= MAX_BYTES):
            files.append(path)
    return files


def test_the_check_finds_a_chronicle_and_passes_a_clean_line():
    assert chronicle_lines("measured in session 20") == [(1, "measured in session 20")]
    for narrated in ("a full disk failed CI at stop 34", "see issue 14, item 2", "part 2 of the review",
                     "figures of earlier sessions", "the session-18 code", "changed in round 3",
                     "as stated 3 sessions ago", "(issue #9)"):
        assert chronicle_lines(narrated), narrated
    for clean in ("the repair keeps unseen faces (repair.mesh.keep_unseen_m, 0.5 m)",
                  "the session's moto S3 server on 127.0.0.1", "one Prefect server per test session",
                  "AWS_SESSION_TOKEN", "round(x, 3) to 3 decimals", "workers stop within 8 s"):
        assert not chronicle_lines(clean), clean


def test_no_tracked_file_narrates_numbered_rounds_of_work():
    files = tracked_text_files()
    assert any(p.name == "README.md" for p in files)
    found = []
    for path in files:
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue  # binary data under a text suffix
        found += [f"{path.relative_to(ROOT)}:{i}: {line[:120]}" for i, line in chronicle_lines(text)]
    assert not found, "chronicle wording (describe the code, date a figure by its commit):\n" + "\n".join(found)
