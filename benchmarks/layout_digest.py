"""Digests of what a run computes on the tiny campus: the patch stores, the grades and tileset.json.

    .venv/bin/python benchmarks/layout_digest.py                         # the working tree's code
    .venv/bin/python benchmarks/layout_digest.py --rev b2050a6           # the code of a commit
    .venv/bin/python benchmarks/layout_digest.py --against b2050a6       # the working tree against a commit
    .venv/bin/python benchmarks/layout_digest.py --against b2050a6 --repeat   # and the working tree twice

A refactor that moves modules must not change what a run computes. This script generates the synthetic
campus (``ms3d synth --preset tiny --seed 0``), runs the whole pipeline on it (``ms3d run`` with the
'inline' runner: one process, no Prefect, no Dask, so nothing depends on scheduling), and prints a SHA-256
per file of

    tiles/*/points.parquet, faces.parquet, patches.parquet   the patch stores
    tiles/*/grades.parquet                                   the grades
    output/tileset.json                                      the 3D Tiles

and one combined digest (SHA-256 of the sorted "path  digest" lines), plus one informational digest of the
generated campus (the inputs: synth's code is compared too).

``--against REV`` also runs the same campus with REV's code (a ``git worktree`` in a temporary folder,
removed afterwards) and prints a table: file, digest at REV, digest now, same / DIFFERENT. Exit code 1
if anything differs, 2 if a run failed (e.g. the working tree is mid-move and does not import).

The pipeline runs in a subprocess of the same Python (this venv) with its cwd and PYTHONPATH at the code's
root, and any other ms3d checkout (the editable install's path entry) taken off ``sys.path``; after the run
it checks that every project module it loaded came from that root. This script imports no ms3d module,
so it works whatever the layout of the code it measures.

Location: the stores depend on where the campus lies. Input source ids are hashes of the input files'
absolute paths (``storage.inputs.assign_source_ids``): column ``source`` of points and faces, and the face
vertex ids ``vid0..2`` built from them; ``faces.parquet`` also records the texture images' absolute paths
(its ``ms3d`` schema metadata, key ``textures``). Every run of one invocation therefore generates and runs
the campus at the same place (``WORK/run/campus`` and ``WORK/run/work``) and then moves it to
``WORK/runs/<label>``; digests printed by separate invocations compare when they used the same ``--work``.

Run-to-run: with ``--repeat`` the current code runs twice and the files whose bytes differ between the two
runs are listed with what differs in their decoded content. None did when this script was written (every
file byte-identical over two runs of the same code at the same place, Parquet 'created_by' included: it
names the pyarrow of the one venv both sides use); should some become volatile, name them in VOLATILE
(with the reason and the keys to drop) and the table compares them by decoded content, saying so.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TILE_FILES = ("points.parquet", "faces.parquet", "patches.parquet", "grades.parquet")
OUTPUT_FILES = ("output/tileset.json",)
PROJECT_PACKAGES = ("flows", "tasks", "storage", "synth", "ms3d_model")

# file name -> (why its bytes differ run to run, the decoded keys to drop before comparing). Parquet: keys of
# the file's key-value metadata, "KEY.SUBKEY" for a key of a JSON-valued entry ("ms3d.textures"), or
# "created_by"; JSON: top-level or dotted keys. Empty: no file differed over two runs of the same code.
VOLATILE: dict[str, tuple[str, tuple[str, ...]]] = {}

# Run in the subprocess: argv = [root, ms3d CLI arguments...]. The code under test is `root`'s alone.
_WRAPPER = r"""
import os, sys
root = os.path.realpath(sys.argv[1])
def _other_checkout(p):
    p = os.path.realpath(p or os.getcwd())
    return p != root and os.path.isfile(os.path.join(p, "pyproject.toml")) and os.path.isdir(os.path.join(p, "flows"))
sys.path[:] = [root] + [p for p in sys.path if os.path.realpath(p or os.getcwd()) != root and not _other_checkout(p)]
try:
    import flows.cli
    rc = flows.cli.main(sys.argv[2:])
finally:
    strays = sorted(f"{n} from {m.__file__}" for n, m in list(sys.modules.items())
                    if n.split(".")[0] in PACKAGES and getattr(m, "__file__", None)
                    and not os.path.realpath(m.__file__).startswith(root + os.sep))
    if strays:
        print("layout_digest: modules from outside " + root + ": " + "; ".join(strays), file=sys.stderr)
        sys.exit(4)
sys.exit(rc)
""".replace("PACKAGES", repr(PROJECT_PACKAGES))


class RunFailed(RuntimeError):
    pass


def _git(*args: str, cwd: Path = REPO) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


@contextmanager
def worktree(rev: str):
    """A detached ``git worktree`` of ``rev`` in a temporary folder; removed on the way out."""
    tmp = Path(tempfile.mkdtemp(prefix="ms3d-layout-digest-"))
    src = tmp / "src"
    try:
        _git("worktree", "add", "--detach", "--quiet", str(src), rev)
        yield src
    finally:
        if src.exists():
            subprocess.run(["git", "worktree", "remove", "--force", str(src)], cwd=REPO, capture_output=True, check=False)
        subprocess.run(["git", "worktree", "prune"], cwd=REPO, capture_output=True, check=False)
        shutil.rmtree(tmp, ignore_errors=True)


def _ms3d(root: Path, args: list[str], log: Path) -> float:
    env = {**os.environ, "PYTHONPATH": str(root)}
    t0 = time.perf_counter()
    with open(log, "a") as f:
        f.write(f"$ ms3d {' '.join(args)}   (code: {root})\n")
        f.flush()
        rc = subprocess.run([sys.executable, "-c", _WRAPPER, str(root), *args], cwd=root, env=env, stdout=f,
                            stderr=subprocess.STDOUT, check=False).returncode
    if rc != 0:
        tail = "\n".join(log.read_text().splitlines()[-15:])
        raise RunFailed(f"`ms3d {args[0]}` with the code at {root} exited {rc}; the end of {log}:\n{tail}")
    return time.perf_counter() - t0


def run_side(root: Path, work: Path, label: str, preset: str, seed: int) -> tuple[Path, float, float]:
    """Generate the campus and run the pipeline with the code at ``root`` at WORK/run, then move it to
    WORK/runs/<label>. Returns (that folder, synth seconds, run seconds)."""
    run = work / "run"
    dest = work / "runs" / label
    shutil.rmtree(run, ignore_errors=True)
    shutil.rmtree(dest, ignore_errors=True)
    run.mkdir(parents=True)
    log = work / f"{label}.log"
    log.unlink(missing_ok=True)
    t_synth = _ms3d(root, ["synth", "--preset", preset, "--seed", str(seed), "--out", str(run / "campus")], log)
    t_run = _ms3d(root, ["run", str(run / "campus" / "campus.yaml"), "--work-dir", str(run / "work"),
                         "--set", "runner=inline"], log)
    dest.parent.mkdir(parents=True, exist_ok=True)
    run.rename(dest)
    return dest, t_synth, t_run


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def digests(side: Path) -> dict[str, str]:
    """rel path (under the work dir) -> SHA-256 of the compared files."""
    wd = side / "work"
    files = [p for p in sorted((wd / "tiles").glob("*/*")) if p.name in TILE_FILES]
    files += [wd / rel for rel in OUTPUT_FILES if (wd / rel).exists()]
    return {p.relative_to(wd).as_posix(): _sha256(p) for p in files}


def combined(d: dict[str, str]) -> str:
    return hashlib.sha256("".join(f"{k}  {v}\n" for k, v in sorted(d.items())).encode()).hexdigest()


def input_digest(side: Path) -> tuple[str, int]:
    """One digest of the generated campus (every file under campus/, by relative path)."""
    root = side / "campus"
    files = sorted(p for p in root.rglob("*") if p.is_file())
    return combined({p.relative_to(root).as_posix(): _sha256(p) for p in files}), len(files)


# --- decoded content --------------------------------------------------------------------------------------

def _drop(doc, dotted: str):
    head, _, rest = dotted.partition(".")
    if isinstance(doc, dict) and head in doc:
        if rest:
            _drop(doc[head], rest)
        else:
            doc.pop(head)


def _parquet_parts(path: Path, drop: tuple[str, ...] = ()) -> dict:
    import pyarrow.parquet as pq

    pf = pq.ParquetFile(path)
    kv = {}
    for k, v in (pf.metadata.metadata or {}).items():
        k = k.decode()
        if k == "ARROW:schema":  # the serialized schema, metadata included: compared through the fields
            continue
        try:
            kv[k] = json.loads(v)
        except ValueError:
            kv[k] = v.decode(errors="replace")
    parts = {"created_by": pf.metadata.created_by, "metadata": kv,
             "schema": [(f.name, str(f.type), f.nullable) for f in pf.schema_arrow],
             "row_groups": [pf.metadata.row_group(i).num_rows for i in range(pf.metadata.num_row_groups)]}
    for d in drop:
        if d == "created_by":
            parts.pop("created_by")
        else:
            _drop(parts["metadata"], d)
    return parts


def content_diff(a: Path, b: Path, drop: tuple[str, ...] = ()) -> list[str]:
    """What differs between two files' decoded content (empty: the same); ``drop``: keys left out."""
    if a.suffix == ".json":
        da, db = json.loads(a.read_text()), json.loads(b.read_text())
        for d in drop:
            _drop(da, d)
            _drop(db, d)
        return [] if da == db else [f"JSON keys {sorted(_json_diff(da, db))[:8]}"]
    import pyarrow.parquet as pq

    out = []
    pa_, pb_ = _parquet_parts(a, drop), _parquet_parts(b, drop)
    for part in ("created_by", "schema", "row_groups"):
        if pa_.get(part) != pb_.get(part):
            out.append(f"{part}: {pa_.get(part)!r} vs {pb_.get(part)!r}"[:300])
    ma, mb = pa_["metadata"], pb_["metadata"]
    for k in sorted(set(ma) | set(mb)):
        if ma.get(k) != mb.get(k):
            keys = sorted(_json_diff(ma.get(k), mb.get(k)))
            out.append(f"metadata '{k}'" + (f" keys {keys[:8]}" if keys else ""))
    ta, tb = pq.read_table(a), pq.read_table(b)
    if ta.schema.names == tb.schema.names and ta.num_rows == tb.num_rows:
        cols = [n for n in ta.schema.names if not ta.column(n).equals(tb.column(n))]
        if cols:
            out.append(f"column values {cols}")
    elif not out:
        out.append("columns or row count")
    return out


def _json_diff(a, b, prefix: str = "") -> set[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        keys = set()
        for k in set(a) | set(b):
            if a.get(k) != b.get(k):
                keys |= _json_diff(a.get(k), b.get(k), f"{prefix}{k}.") or {f"{prefix}{k}"}
        return keys
    return set() if a == b else ({prefix.rstrip(".")} if prefix else set())


def _volatile(rel: str) -> tuple[str, tuple[str, ...]] | None:
    return VOLATILE.get(rel.rsplit("/", 1)[-1])


# --- reports ----------------------------------------------------------------------------------------------

def compare(a_side: Path, b_side: Path, da: dict[str, str], db: dict[str, str]) -> list[tuple[str, str, str, str]]:
    """Rows (file, digest a, digest b, verdict); verdicts starting with 'DIFFERENT' or 'missing' fail."""
    rows = []
    for rel in sorted(set(da) | set(db)):
        ha, hb = da.get(rel, "(missing)"), db.get(rel, "(missing)")
        if rel not in da or rel not in db:
            verdict = "DIFFERENT (file missing on one side)"
        elif ha == hb:
            verdict = "same"
        else:
            vol = _volatile(rel)
            diff = content_diff(a_side / "work" / rel, b_side / "work" / rel, vol[1] if vol else ())
            if vol and not diff:
                verdict = f"same by decoded content, without {', '.join(vol[1])} ({vol[0]})"
            else:
                verdict = "DIFFERENT: " + ("; ".join(diff) if diff else "bytes only (decoded content same)")
        rows.append((rel, ha, hb, verdict))
    return rows


def print_digests(label: str, d: dict[str, str], inp: tuple[str, int]) -> None:
    print(f"\n{label}:")
    w = max(map(len, d), default=10)
    for rel, h in sorted(d.items()):
        print(f"  {rel:<{w}}  {h}")
    print(f"  {'combined (' + str(len(d)) + ' files)':<{w}}  {combined(d)}")
    print(f"  {'input campus (' + str(inp[1]) + ' files)':<{w}}  {inp[0]}")


def print_table(rows, head_a: str, head_b: str) -> None:
    w = max(len(r[0]) for r in rows)
    hw = max(64, len(head_a), len(head_b))
    print(f"\n{'file':<{w}}  {head_a:<{hw}}  {head_b:<{hw}}  verdict")
    print(f"{'-' * w}  {'-' * hw}  {'-' * hw}  {'-' * 7}")
    for rel, ha, hb, v in rows:
        print(f"{rel:<{w}}  {ha:<{hw}}  {hb:<{hw}}  {v}")


def _failed(verdict: str) -> bool:
    return verdict.startswith("DIFFERENT")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rev", help="measure the code of this commit (a git worktree) instead of the working tree")
    ap.add_argument("--against", metavar="REV", help="also run REV's code and compare, file by file")
    ap.add_argument("--work", default=str(REPO / "ms3d-work" / "layout-digest"),
                    help="where the campus is generated and run (default ms3d-work/layout-digest)")
    ap.add_argument("--preset", default="tiny", choices=("tiny", "demo", "campus"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", action="store_true",
                    help="run the measured code twice and list the files whose bytes differ run to run")
    a = ap.parse_args(argv)
    work = Path(a.work).absolute()
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def side(rev: str | None, label: str):
        desc = f"{rev} ({_git('rev-parse', '--short', rev + '^{commit}')})" if rev else \
            f"working tree {REPO} (HEAD {_git('rev-parse', '--short', 'HEAD')}, with its uncommitted changes)"
        print(f"[{label}] {desc}: synth --preset {a.preset} --seed {a.seed}, run (inline) ...", flush=True)
        if rev:
            with worktree(rev) as src:
                out = run_side(src, work, label, a.preset, a.seed)
        else:
            out = run_side(REPO, work, label, a.preset, a.seed)
        print(f"[{label}] synth {out[1]:.1f} s, pipeline {out[2]:.1f} s -> {out[0]}", flush=True)
        return out[0], desc

    rc = 0
    try:
        sides = {}
        if a.against:
            sides["rev"] = side(a.against, "rev")
        sides["now"] = side(a.rev, "now")
        if a.repeat:
            sides["now2"] = side(a.rev, "now2")
    except RunFailed as e:
        print(f"layout_digest: error: {e}", file=sys.stderr)
        return 2

    d = {k: digests(v[0]) for k, v in sides.items()}
    inputs = {k: input_digest(v[0]) for k, v in sides.items()}
    for k, (path, desc) in sides.items():
        print_digests(f"{k}: {desc}", d[k], inputs[k])

    if a.repeat:
        rows = compare(sides["now"][0], sides["now2"][0], d["now"], d["now2"])
        bad = [r for r in rows if r[3] != "same"]
        print(f"\nrun to run (the measured code twice, same place): "
              f"{'every file byte-identical' if not bad else str(len(bad)) + ' file(s) differ'}"
              f"{'' if inputs['now'][0] == inputs['now2'][0] else '; the generated campus differs too'}")
        for rel, _, _, v in bad:
            print(f"  {rel}: {v}")
        if bad:
            rc = 1

    if a.against:
        rows = compare(sides["rev"][0], sides["now"][0], d["rev"], d["now"])
        same_in = inputs["rev"][0] == inputs["now"][0]
        rows.append((f"input campus ({inputs['now'][1]} files)", inputs["rev"][0], inputs["now"][0],
                     "same" if same_in else "DIFFERENT (the generated campus)"))
        rows.append((f"combined ({len(d['now'])} files)", combined(d["rev"]), combined(d["now"]),
                     "same" if combined(d["rev"]) == combined(d["now"]) else "DIFFERENT"))
        print_table(rows, f"at {a.against}", "now" if not a.rev else f"at {a.rev}")
        n_bad = sum(_failed(r[3]) for r in rows[:-1])  # the combined row follows from the others
        print(f"\n{'all same' if not n_bad else str(n_bad) + ' row(s) DIFFERENT'}: {len(d['now'])} files "
              f"(stores, grades, tileset.json) of the {a.preset} campus, seed {a.seed}")
        if n_bad:
            rc = 1
    print(f"wall {time.perf_counter() - t0:.1f} s")
    return rc


if __name__ == "__main__":
    sys.exit(main())
