"""The layout rules of the code base (docs/design.md), checked statically with ``ast``, nothing imported:

(a) no module over 400 lines; (b) no function over 80 lines (both: non-test code);
(c) a stage package (a subpackage of ``tasks`` other than ``config`` and ``geometry``) imports another
    stage only through the names in that stage's ``__all__``: never one of its submodules, never a
    ``_private`` name; ``flows/`` likewise;
(d) in a stage package only ``stage.py`` (and ``__init__.py``) touch the WorkDir, the manifest or the units
    (``storage.workdir.layout``, ``storage.workdir.manifest``, ``tasks.units``);
(e) every stage package's docstring says what it reads, what it writes and what invalidates it;
(f) in a stage package only ``stage.py`` (and ``__init__.py``) read or write files: no ``open``,
    ``np.load`` / ``np.save*``, ``pq.read_*`` / ``pq.write_*``, ``json.load`` / ``json.dump``, PIL's
    ``Image.open``, ``laspy.open`` / ``laspy.read``, nor a ``.read_text`` / ``.read_bytes`` / ``.write_text`` /
    ``.write_bytes`` call elsewhere; the pure modules take arrays and return arrays. File formats belong in
    ``storage/``. The few modules still doing I/O are in :data:`IO_ALLOWED`, each with its reason.

Each check returns ``file:line: problem`` strings; the self-tests at the bottom feed the checkers
offending sources, so a check that cannot fail would show.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CODE_DIRS = ("flows", "tasks", "storage", "synth", "ms3d_model", "benchmarks")
SHARED_TASK_PACKAGES = {"config", "geometry"}  # shared by every stage: not stage packages
STAGE_ONLY_MODULES = ("storage.workdir", "tasks.units")  # packages / modules, with everything inside them
MAX_MODULE_LINES = 400
MAX_FUNCTION_LINES = 80
# Rule (f): calls that read or write files, by the dotted name they resolve to through the module's imports
IO_CALLS = frozenset({"open", "io.open", "numpy.load", "numpy.loadtxt", "numpy.fromfile", "numpy.save",
                      "numpy.savez", "numpy.savez_compressed", "numpy.savetxt", "json.load", "json.dump",
                      "PIL.Image.open", "laspy.open", "laspy.read", "pyarrow.parquet.ParquetFile",
                      "pyarrow.parquet.ParquetWriter"})
IO_PREFIXES = ("pyarrow.parquet.read_", "pyarrow.parquet.write_")
IO_METHODS = frozenset({"read_text", "read_bytes", "write_text", "write_bytes"})  # pathlib's, on any object
# Rule (f)'s exceptions: modules of stage packages that still read or write files, and why.
IO_ALLOWED = {
    # a command-line checker of an export on disk (``python -m tasks.export.check WORKDIR``, and the tests'):
    # reading the tileset and glbs it validates is its job; no stage runs it
    "tasks/export/check.py": "validates the files of an export",
    # its LOD cache (save_lod / load_lod, .npz) moves to storage.formats.arrays once the decimator
    # replacement being made in this module lands (edited by another change meanwhile)
    "tasks/export/lod.py": "LOD cache .npz, pending the decimator change",
    # the report stage's package is being reworked (its resume logic into the stage) by another change;
    # its section builders read recorded JSON, the figures' PNGs and output/tileset.json
    "tasks/report/sections.py": "report stage under rework",
}


@dataclass(frozen=True)
class Module:
    """One source file: ``rel`` its path from the repo root (posix), ``source`` its text."""

    rel: str
    source: str

    @property
    def name(self) -> str:
        parts = self.rel.removesuffix(".py").split("/")
        return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)

    @property
    def package(self) -> str:
        """The package relative imports start from."""
        return self.name if self.rel.endswith("__init__.py") else self.name.rpartition(".")[0]

    def tree(self) -> ast.Module:
        return ast.parse(self.source, filename=self.rel)


def code_modules() -> list[Module]:
    """Every Python file of the code directories (tests live elsewhere)."""
    return [Module(p.relative_to(ROOT).as_posix(), p.read_text())
            for d in CODE_DIRS for p in sorted((ROOT / d).rglob("*.py"))]


def stage_packages(root: Path = ROOT) -> list[str]:
    return sorted(p.parent.name for p in (root / "tasks").glob("*/__init__.py")
                  if p.parent.name not in SHARED_TASK_PACKAGES)


def static_all(source: str) -> set[str]:
    """The names a module lists in ``__all__`` (assignments and ``+=`` of literal lists/tuples)."""
    names: set[str] = set()
    for node in ast.parse(source).body:
        targets = (node.targets if isinstance(node, ast.Assign) else
                   [node.target] if isinstance(node, (ast.AnnAssign, ast.AugAssign)) else [])
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets) and node.value is not None:
            try:
                names |= set(ast.literal_eval(node.value))
            except ValueError:
                pass
    return names


def stage_exports(root: Path = ROOT) -> dict[str, set[str]]:
    """Stage package -> the names of its ``__all__``, read without importing it."""
    return {pkg: static_all((root / "tasks" / pkg / "__init__.py").read_text()) for pkg in stage_packages(root)}


# ------------------------------------------------------------------------------------------------ checks

def check_module_size(m: Module, limit: int = MAX_MODULE_LINES) -> list[str]:
    n = len(m.source.splitlines())
    return [f"{m.rel}:{n}: {n} lines (limit {limit})"] if n > limit else []


def check_function_size(m: Module, limit: int = MAX_FUNCTION_LINES) -> list[str]:
    out = []
    for node in ast.walk(m.tree()):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            n = node.end_lineno - node.lineno + 1
            if n > limit:
                out.append(f"{m.rel}:{node.lineno}: function {node.name} has {n} lines (limit {limit})")
    return out


def imports(m: Module) -> list[tuple[int, str, str | None]]:
    """Every import of ``m``, module level or not: (line, absolute module, imported name or None)."""
    out = []
    for node in ast.walk(m.tree()):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = m.package.split(".")
                pkg = pkg[:len(pkg) - (node.level - 1)]
                base = ".".join(pkg + ([base] if base else []))
            out += [(node.lineno, base, a.name) for a in node.names]
    return out


def _stage_of(module: str, stages: set[str]) -> tuple[str | None, str]:
    """('merge', 'kernels') for 'tasks.merge.kernels', ('merge', '') for 'tasks.merge', (None, '') else."""
    parts = module.split(".")
    if len(parts) >= 2 and parts[0] == "tasks" and parts[1] in stages:
        return parts[1], ".".join(parts[2:])
    return None, ""


def check_stage_imports(m: Module, exports: dict[str, set[str]]) -> list[str]:
    """Rule (c) for a module of ``tasks/<stage>/`` or ``flows/``: other stages only via their ``__all__``."""
    stages = set(exports)
    own, _ = _stage_of(m.name, stages)
    out = []
    for line, module, name in imports(m):
        if module == "tasks" and name in stages and name != own:
            module, name = f"tasks.{name}", None  # `from tasks import merge`: the package object
        stage, sub = _stage_of(module, stages)
        if stage is None or stage == own:
            continue
        where = f"{m.rel}:{line}"
        if sub:
            out.append(f"{where}: imports {module}, a module inside stage package tasks.{stage} "
                       f"(import the names of tasks.{stage}.__all__)")
        elif name is None:
            out.append(f"{where}: imports the package tasks.{stage} whole (import names of its __all__)")
        elif name.startswith("_"):
            out.append(f"{where}: imports private {name} from tasks.{stage}")
        elif name not in exports[stage]:
            out.append(f"{where}: imports {name} from tasks.{stage}, which is not in its __all__")
    return out


def check_stage_only_imports(m: Module, stages: set[str]) -> list[str]:
    """Rule (d): WorkDir, manifest and units belong to a stage package's ``stage.py``."""
    stage, sub = _stage_of(m.name, stages)
    if stage is None or sub in ("", "stage"):
        return []
    out = []
    for line, module, name in imports(m):
        full = f"{module}.{name}" if name else module
        if full.startswith(STAGE_ONLY_MODULES) or module.startswith(STAGE_ONLY_MODULES):
            out.append(f"{m.rel}:{line}: imports {full}; only stage.py of tasks.{stage} may")
    return out


def check_stage_docstring(m: Module) -> list[str]:
    """Rule (e), for a stage package's ``__init__.py``."""
    doc = (ast.get_docstring(m.tree()) or "").lower()
    missing = [w for w in ("reads", "writes", "invalidat") if w not in doc]
    return [f"{m.rel}:1: docstring does not say what the stage {' / '.join(missing)}"] if missing else []


def _import_aliases(tree: ast.Module) -> dict[str, str]:
    """Local name -> the dotted name it stands for, from every import of the module (at any depth)."""
    names: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                names[a.asname or a.name.partition(".")[0]] = a.name if a.asname else a.name.partition(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                names[a.asname or a.name] = f"{node.module}.{a.name}"
    return names


def _dotted(func: ast.expr, aliases: dict[str, str]) -> str | None:
    """The dotted name a call's function resolves to (``np.load`` -> ``numpy.load``), None if not a name."""
    parts = []
    while isinstance(func, ast.Attribute):
        parts.append(func.attr)
        func = func.value
    if not isinstance(func, ast.Name):
        return None
    return ".".join([aliases.get(func.id, func.id), *reversed(parts)])


def check_no_file_io(m: Module, stages: set[str]) -> list[str]:
    """Rule (f), for a module of a stage package other than its ``stage.py`` and ``__init__.py``."""
    stage, sub = _stage_of(m.name, stages)
    if stage is None or sub in ("", "stage"):
        return []
    tree = m.tree()
    aliases = _import_aliases(tree)
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        name = _dotted(node.func, aliases)
        method = node.func.attr if isinstance(node.func, ast.Attribute) else None
        if (name in IO_CALLS or (name or "").startswith(IO_PREFIXES)) or method in IO_METHODS:
            out.append((node.lineno, f"{m.rel}:{node.lineno}: calls {name or method}: file I/O belongs in "
                                     f"stage.py of tasks.{stage} (or a storage/ format)"))
    return [p for _, p in sorted(out)]


# ------------------------------------------------------------------------------------------ the tree

def _report(problems: list[str]) -> str:
    return f"{len(problems)} violation(s):\n" + "\n".join(problems)


def test_no_module_over_400_lines():
    problems = [p for m in code_modules() for p in check_module_size(m)]
    assert not problems, _report(problems)


def test_no_function_over_80_lines():
    problems = [p for m in code_modules() for p in check_function_size(m)]
    assert not problems, _report(problems)


def test_stages_and_flows_import_other_stages_only_through_their_public_names():
    exports = stage_exports()
    problems = [p for m in code_modules() if m.rel.startswith(("tasks/", "flows/"))
                for p in check_stage_imports(m, exports)]
    assert not problems, _report(problems)


def test_only_stage_modules_touch_the_workdir_manifest_and_units():
    stages = set(stage_packages())
    problems = [p for m in code_modules() if m.rel.startswith("tasks/") for p in check_stage_only_imports(m, stages)]
    assert not problems, _report(problems)


def test_only_stage_modules_read_or_write_files():
    stages = set(stage_packages())
    problems = [p for m in code_modules() if m.rel.startswith("tasks/") and m.rel not in IO_ALLOWED
                for p in check_no_file_io(m, stages)]
    assert not problems, _report(problems)
    stale = [rel for rel in IO_ALLOWED if not (ROOT / rel).exists()
             or not check_no_file_io(Module(rel, (ROOT / rel).read_text()), stages)]
    assert not stale, f"IO_ALLOWED names modules that no longer do file I/O (drop them): {stale}"


def test_every_stage_package_says_what_it_reads_writes_and_what_invalidates_it():
    assert len(stage_packages()) >= 5  # the glob found the stage packages
    problems = [p for pkg in stage_packages()
                for p in check_stage_docstring(Module(f"tasks/{pkg}/__init__.py",
                                                      (ROOT / "tasks" / pkg / "__init__.py").read_text()))]
    assert not problems, _report(problems)


# ------------------------------------------------------------------------------- the checkers can fail

EXPORTS = {"merge": {"merge_tile"}, "repair": {"patch_grades", "RepairConfig"}}


def test_checkers_catch_long_modules_and_functions():
    def function(n_body: int) -> str:
        return "def f():\n" + "".join(f"    x = {i}\n" for i in range(n_body))

    assert check_function_size(Module("synth/big.py", "import os\n\n\n" + function(81))) == [
        "synth/big.py:4: function f has 82 lines (limit 80)"]
    assert check_function_size(Module("synth/ok.py", function(79))) == []
    assert check_module_size(Module("synth/big.py", "x = 1\n" * 401)) == ["synth/big.py:401: 401 lines (limit 400)"]
    assert check_module_size(Module("synth/ok.py", "x = 1\n" * 400)) == []


def test_checker_catches_imports_of_another_stages_insides():
    lines = [
        "from tasks.repair import patch_grades",  # 1: public, fine
        "from tasks.repair.grades import patch_grades",  # 2: a module inside repair
        "from tasks.repair import _texture_maths",  # 3: private
        "from tasks.repair import helper",  # 4: not in __all__
        "from ..repair import grades",  # 5: relative, a submodule (not exported)
        "from .kernels import x",  # 6: own package, fine
        "from tasks.config import CampusConfig",  # 7: shared, fine
        "def f():",
        "    import tasks.repair.region_io",  # 9: function level, inside repair
        "    from tasks import repair",  # 10: the package whole
    ]
    src = "\n".join(lines)
    got = check_stage_imports(Module("tasks/merge/kernels.py", src), EXPORTS)
    assert [p.split(":")[1] for p in got] == ["2", "3", "4", "5", "9", "10"], got
    assert got[1] == "tasks/merge/kernels.py:3: imports private _texture_maths from tasks.repair"
    flows = check_stage_imports(Module("flows/tasks.py", "from tasks.merge.stage import run_merge_tile\n"
                                                          "from tasks.merge import merge_tile\n"), EXPORTS)
    assert len(flows) == 1 and flows[0].startswith("flows/tasks.py:1: imports tasks.merge.stage")


def test_checker_catches_workdir_outside_stage_py():
    stages = set(EXPORTS)
    src = "from storage.workdir.layout import WorkDir\nfrom storage.workdir import manifest\nfrom ..units import run_unit\n"
    got = check_stage_only_imports(Module("tasks/merge/kernels.py", src), stages)
    assert [p.split(":")[1] for p in got] == ["1", "2", "3"], got
    assert check_stage_only_imports(Module("tasks/merge/stage.py", src), stages) == []
    assert check_stage_only_imports(Module("tasks/merge/__init__.py", src), stages) == []


def test_checker_catches_a_stage_docstring_without_its_contract():
    assert check_stage_docstring(Module("tasks/merge/__init__.py", '"""Merge: reads patches, writes meshes."""\n')) \
        == ["tasks/merge/__init__.py:1: docstring does not say what the stage invalidat"]
    ok = '"""Merge. Reads patches; writes meshes; invalidated by a new partition."""\n'
    assert check_stage_docstring(Module("tasks/merge/__init__.py", ok)) == []


def test_checker_catches_file_io_outside_stage_py():
    stages = set(EXPORTS)
    lines = [
        "import json, numpy",  # 1
        "import numpy as np",  # 2
        "import pyarrow.parquet as pq",  # 3
        "from PIL import Image",  # 4
        "from json import dump as save_json",  # 5
        "def f(path, buf):",  # 6
        "    a = np.load(path)",  # 7
        "    numpy.savez(path, a=a)",  # 8
        "    t = pq.read_table(path)",  # 9
        "    pq.write_table(t, path)",  # 10
        "    doc = json.load(open(path))",  # 11: json.load and open
        "    save_json(doc, buf)",  # 12
        "    text = path.read_text() + path.with_suffix('.x').read_bytes().decode()",  # 13: both
        "    Image.open(path)",  # 14
        "    return json.loads(text), np.asarray(a), pq.ParquetFile(path)",  # 15: ParquetFile only
    ]
    src = "\n".join(lines) + "\n"
    got = check_no_file_io(Module("tasks/merge/kernels.py", src), stages)
    assert sorted(int(p.split(":")[1]) for p in got) == [7, 8, 9, 10, 11, 11, 12, 13, 13, 14, 15], got
    assert got[0].startswith("tasks/merge/kernels.py:7: calls numpy.load")
    assert check_no_file_io(Module("tasks/merge/stage.py", src), stages) == []
    assert check_no_file_io(Module("tasks/merge/__init__.py", src), stages) == []
    assert check_no_file_io(Module("tasks/geometry/sampling.py", src), stages) == []  # not a stage package
    clean = "import json\nimport numpy as np\ndef f(doc, a):\n    return json.dumps(doc), np.save_like(a), a.open\n"
    assert check_no_file_io(Module("tasks/merge/kernels.py", clean), stages) == []


def test_static_all_reads_literal_lists_and_additions():
    assert static_all("__all__ = ['a', 'b']\n__all__ += ('c',)\nx = 1\n") == {"a", "b", "c"}


@pytest.mark.parametrize("rel, name, package", [("tasks/merge/__init__.py", "tasks.merge", "tasks.merge"),
                                                ("tasks/merge/stage.py", "tasks.merge.stage", "tasks.merge")])
def test_module_names(rel, name, package):
    assert (Module(rel, "").name, Module(rel, "").package) == (name, package)
