"""The bad-input table: what a user sees for each kind of bad input, the exit code, and the tiles done and
failed, on a campus whose previous run succeeded (so "nothing lost" can be checked: every tile the bad
input does not touch keeps its store, byte for byte).

    .venv/bin/python benchmarks/bad_inputs.py [--markdown] [--only NAME ...]

Each case starts from a freshly built good campus (``synth.handmade``: three regions, each with a mesh and
a LAZ file, 20 m tiles) and its finished work dir, breaks one thing, and runs ``ms3d run`` (inline
runner) through the CLI's own ``main``. ``tests/flows/test_bad_inputs.py`` asserts the same cases.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import hashlib
import io
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bad_cases import CASES, Case, set_cfg

# ------------------------------------------------------------------------------------------ running


def _checksums(work: Path) -> dict[str, str]:
    return {str(p.relative_to(work)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted((work / "tiles").glob("*/*.parquet"))}


# False: the campus runs without classify, repair and the report (the test suite's sample, for time; the
# bad inputs all fail in scan, ingest or partition, and the table itself runs the whole pipeline)
LATER_STAGES = True


def prepare(root: Path) -> None:
    """A good campus in ``root`` and its finished work dir ``root/work``."""
    from flows.cli import main
    from synth.handmade import build_campus

    shutil.rmtree(root, ignore_errors=True)
    build_campus(root, tile_size_m=20.0)
    set_cfg(root, work_dir="work", runner="inline")
    if not LATER_STAGES:
        set_cfg(root, **{"classify.enabled": False, "repair.enabled": False, "report.enabled": False})
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", str(root / "campus.yaml")]) == 0


def _du(path: Path) -> int:
    """Bytes a folder takes on a tmpfs (whole 4 KiB pages per file and folder)."""
    return sum(-(-p.stat().st_size // 4096) * 4096 if p.is_file() else 4096 for p in [path, *path.rglob("*")])


@contextlib.contextmanager
def _tmpfs(path: Path, size: str, read_only: bool = False):
    path.mkdir(parents=True, exist_ok=True)
    opts = f"size={size}" + (",ro" if read_only else "")
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)], capture_output=True, check=False).returncode == 0
    try:
        yield ok
    finally:
        if ok:
            subprocess.run(["umount", "-l", str(path)], capture_output=True, check=False)


def _simulated_enospc():
    """Without a tmpfs (not root), the disk fills when the first tile store is written."""
    import pyarrow.parquet as pq

    real = pq.write_table

    def full(table, where, *a, **k):
        if "/tiles/" in str(where):
            raise OSError(errno.ENOSPC, "No space left on device", str(where))
        return real(table, where, *a, **k)

    return full


def run_case(case: Case, base: Path) -> dict:
    from flows.cli import main
    from storage.patches.read import PatchStore

    root = base / case.name
    prepare(root)
    work = root / "work"
    before = _checksums(work)
    extra = case.breaks(root) or []
    args = ["run", str(root / "campus.yaml")]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.ExitStack() as stack:
        if extra in (["FULL_DISK"], ["READ_ONLY"]):
            disk = root / "disk"
            if extra == ["FULL_DISK"]:  # the old work dir on a disk with ~150 kB to spare, then a new strip
                size = _du(work) + 150_000
                mounted = stack.enter_context(_tmpfs(disk, str(size)))
                if mounted:
                    shutil.copytree(work, disk / "work")
                from storage.formats.points import read_points, write_points

                pc = read_points(root / "mls" / "east.laz")
                pc.xyz = pc.xyz + [0.0, 0.0, 0.05]
                write_points(root / "mls" / "east-day2.laz", pc, crs="EPSG:32650")
            else:
                mounted = stack.enter_context(_tmpfs(disk, "1m", read_only=True))
            if mounted:
                work = disk / "work"
                args += ["--work-dir", str(work)]
            elif extra == ["FULL_DISK"]:
                import pyarrow.parquet as pq

                stack.enter_context(_patched(pq, "write_table", _simulated_enospc()))
            else:
                work.chmod(0o555)  # not root: permissions apply
            before = _checksums(work) if (work / "tiles").exists() else {}
            extra = []
        stack.enter_context(contextlib.redirect_stdout(out))
        stack.enter_context(contextlib.redirect_stderr(err))
        code = main(args + extra)
        tiles_done = tiles_failed = 0
        readable = True
        if (work / "manifest.d" / "partition").exists():
            from flows.status import campus_status

            with contextlib.suppress(Exception):
                st = campus_status(str(work))
                tiles_done, tiles_failed = len(st["done"]), len(st["failed"])
            for t in (work / "tiles").glob("*"):
                if (t / "patches.parquet").exists():
                    try:
                        PatchStore(t)
                    except Exception:  # noqa: BLE001 - the table reports it
                        readable = False
        after = _checksums(work) if (work / "tiles").exists() else {}
    with contextlib.suppress(OSError):
        (root / "work").chmod(0o755)
    lost = sorted(k for k, v in before.items() if k in after and after[k] != v and not _touched(case, k))
    missing = sorted(k for k in before if k not in after and not _touched(case, k))
    err_lines = [line for line in err.getvalue().splitlines() if line.strip()]
    return {"case": case, "code": code, "stderr": err_lines, "stdout": out.getvalue(), "tiles_done": tiles_done,
            "tiles_failed": tiles_failed, "readable": readable, "changed_untouched": lost + missing}


def _touched(case: Case, rel: str) -> bool:
    """Stores a case may legitimately change: those of the region whose input it breaks."""
    region = {"truncated-laz": "west", "nan-vertex": "middle", "missing-mtl": "middle", "missing-texture": "middle",
              "bad-index": "east", "degenerate-faces": "middle", "empty-mesh": "middle", "full-disk": "east"}.get(case.name)
    if region is None:
        return False
    x = int(rel.split("/")[1].split("_")[0]) * 20 - 500_000
    return {"west": x < 45, "middle": 45 <= x < 105, "east": x >= 105}[region]


@contextlib.contextmanager
def _patched(obj, name, value):
    old = getattr(obj, name)
    setattr(obj, name, value)
    try:
        yield
    finally:
        setattr(obj, name, old)


def check(result: dict) -> list[str]:
    """Problems with a case's outcome (empty when it behaves as promised)."""
    c: Case = result["case"]
    problems = []
    if result["code"] != c.code:
        problems.append(f"exit {result['code']}, expected {c.code}")
    text = result["stdout"] + "\n".join(result["stderr"])
    if c.says not in text:
        problems.append(f"does not say {c.says!r}")
    if c.code != 0 and (len(result["stderr"]) != 1 or not result["stderr"][0].startswith("ms3d: error: ")):
        problems.append(f"stderr is not one 'ms3d: error:' line: {result['stderr'][:4]}")
    if any("Traceback" in line for line in result["stderr"]) or "Traceback" in result["stdout"]:
        problems.append("a traceback was printed")
    if not result["readable"]:
        problems.append("a store is unreadable")
    if result["changed_untouched"]:
        problems.append(f"stores of untouched tiles changed: {result['changed_untouched'][:3]}")
    return problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--work", type=Path, default=None)
    a = ap.parse_args(argv)
    base = a.work or Path(tempfile.mkdtemp(prefix="ms3d-bad-inputs-"))
    rows, bad = [], 0
    for case in CASES:
        if a.only and case.name not in a.only:
            continue
        r = run_case(case, base)
        problems = check(r)
        bad += bool(problems)
        seen = r["stderr"][-1] if r["stderr"] else next(
            (line for line in r["stdout"].splitlines() if case.says in line), r["stdout"].splitlines()[-1:])
        rows.append((case.name, case.what, str(seen).replace(str(base), "…"), r["code"], r["tiles_done"],
                     r["tiles_failed"], "ok" if not problems else "; ".join(problems)))
    if a.markdown:
        print("| case | input | what the user sees | exit | tiles done | tiles failed | check |")
        print("|---|---|---|---|---|---|---|")
        for row in rows:
            print("| " + " | ".join(str(v).replace("|", "\\|") for v in row) + " |")
    else:
        for row in rows:
            print(f"{row[0]:<18} exit {row[3]}  done {row[4]:>2} failed {row[5]:>2}  {row[6]}\n    {row[2]}")
    print(f"\n{len(rows) - bad} of {len(rows)} cases behave as promised")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
