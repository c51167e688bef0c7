"""The worked examples in the docstrings run, and say what they print.

Only modules whose text holds a ``>>>`` example are imported (found by reading the files, not by
importing every module), one test per module, each run with ``doctest.testmod``. Examples marked
``# doctest: +SKIP`` (they need files) are found but not run.
"""

from __future__ import annotations

import doctest
import importlib
import re
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("flows", "tasks", "storage", "ms3d_model", "synth")
EXAMPLE = re.compile(r"^\s*>>> ", re.MULTILINE)


def modules_with_examples() -> list[str]:
    found = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if EXAMPLE.search(path.read_text()):
                parts = path.relative_to(ROOT).with_suffix("").parts
                found.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return found


MODULES = modules_with_examples()


def test_the_search_finds_the_examples():
    assert "storage.grid" in MODULES and len(MODULES) >= 10


def run_examples(module) -> tuple[int, int, int]:
    """(examples found, run, failed) of ``module``'s docstrings."""
    found = sum(len(t.examples) for t in doctest.DocTestFinder().find(module))
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False,
                             report=False)
    return found, result.attempted, result.failed


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    found, attempted, failed = run_examples(importlib.import_module(name))
    assert found > 0, f"{name}: no example found (a '>>>' outside a docstring?)"
    assert failed == 0, f"{name}: {failed} of {attempted} examples failed (run " \
                        f"`python -m doctest -v {name.replace('.', '/')}.py` to see them)"


def test_a_wrong_example_fails():
    module = types.ModuleType("wrong_example", ">>> 1 + 1\n3\n>>> 2  # doctest: +SKIP\n5\n")
    assert run_examples(module) == (2, 1, 1)
