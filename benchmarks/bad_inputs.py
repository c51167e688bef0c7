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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


@dataclass(frozen=True)
class Case:
    name: str
    what: str
    breaks: Callable[[Path], list[str] | None]  # mutates the campus folder; returns extra CLI args or None
    code: int  # expected exit code
    says: str  # expected fragment of the error line (stderr) or, for exit 0, of stdout


# ------------------------------------------------------------------------------------------ mutations


def _cfg(root: Path) -> dict:
    return yaml.safe_load((root / "campus.yaml").read_text())


def _set_cfg(root: Path, **changes) -> None:
    doc = _cfg(root)
    for dotted, value in changes.items():
        d = doc
        keys = dotted.split(".")
        for k in keys[:-1]:
            d = d.setdefault(k, {})
        d[keys[-1]] = value
    (root / "campus.yaml").write_text(yaml.safe_dump(doc))


def _truncate(p: Path, keep: float = 0.5) -> None:
    p.write_bytes(p.read_bytes()[: int(p.stat().st_size * keep)])


def _obj_edit(root: Path, name: str, edit) -> None:
    p = root / "mesh" / name
    lines = p.read_text().splitlines()
    p.write_text("\n".join(edit(lines)) + "\n")


def _nan_vertex(lines):
    i = next(k for k, line in enumerate(lines) if line.startswith("v "))
    lines[i] = "v nan 1.0 2.0"
    return lines


def _bad_index(lines):
    i = next(k for k, line in enumerate(lines) if line.startswith("f "))
    lines[i] = "f 1 2 999999"
    return lines


def _textured(root: Path, missing: str) -> None:
    """Give middle.obj a material library and a texture, then remove one of them."""
    from PIL import Image

    p = root / "mesh" / "middle.obj"
    lines = p.read_text().splitlines()
    n_v = sum(1 for line in lines if line.startswith("v "))
    out = ["mtllib middle.mtl", "usemtl facade"] + [line for line in lines if not line.startswith("f ")]
    out += [f"vt {0.1 + 0.8 * (k % 7) / 7:.3f} {0.1 + 0.8 * (k % 5) / 5:.3f}" for k in range(n_v)]
    out += ["f " + " ".join(f"{int(t)}/{int(t)}" for t in line.split()[1:]) for line in lines if line.startswith("f ")]
    p.write_text("\n".join(out) + "\n")
    (root / "mesh" / "middle.mtl").write_text("newmtl facade\nmap_Kd facade.jpg\n")
    Image.fromarray(np.full((8, 8, 3), 128, np.uint8)).save(root / "mesh" / "facade.jpg")
    (root / "mesh" / ("middle.mtl" if missing == "mtl" else "facade.jpg")).unlink()


def _empty_mesh(root: Path) -> None:
    (root / "mesh" / "middle.obj").write_text("# exported with no geometry\n")


def _geographic(root: Path) -> None:
    _set_cfg(root, **{"inputs.crs": "EPSG:4326"})


def _wrong_zone(root: Path) -> None:
    _set_cfg(root, **{"inputs.crs": "EPSG:32651"})  # the LAS headers say EPSG:32650


def _mesh_10km_off(root: Path) -> None:
    o = _cfg(root)["inputs"]["mesh_offset"]
    _set_cfg(root, **{"inputs.mesh_offset": [o[0] + 10_000.0, o[1], o[2]]})


def _no_overlap(root: Path) -> None:
    from storage.pointcloud_io import read_points, write_points

    for p in (root / "mls").glob("*.laz"):
        pc = read_points(p)
        pc.xyz = pc.xyz + [0.0, 3_000.0, 0.0]
        write_points(p, pc, crs="EPSG:32650")


def _feet(root: Path) -> None:
    _set_cfg(root, **{"inputs.units_scale": 0.3048})  # metres declared as US feet


def _read_only(root: Path) -> list[str]:
    return ["READ_ONLY"]


def _points_nan_ply(root: Path) -> None:
    xyz = np.tile([70.0, 10.0, 1.0], (10, 1)) + np.asarray(_cfg(root)["inputs"]["mesh_offset"])
    xyz[0, 0] = np.nan
    head = f"ply\nformat ascii 1.0\nelement vertex {len(xyz)}\nproperty double x\nproperty double y\nproperty double z\nend_header\n"
    (root / "mls" / "handheld.ply").write_text(head + "".join(f"{x} {y} {z}\n" for x, y, z in xyz))


def _corrupt_glb(root: Path) -> None:
    (root / "mesh" / "extra.glb").write_bytes(b"glTF" + b"\x02\x00\x00\x00" + b"\xff" * 64)


def _labels_missing(root: Path) -> None:
    _set_cfg(root, **{"inputs.labels": "truth/missing.json"})


def _degenerate_faces(root: Path) -> None:
    def edit(lines):
        return lines + ["f 1 1 2", "f 3 4 3", "f 1 2 3", "f 1 2 3"]  # repeated ids, duplicates: dropped, counted
    _obj_edit(root, "middle.obj", edit)


def _unit(fn):
    """Wrap a mutation that returns nothing."""
    def wrapped(root: Path):
        fn(root)
    return wrapped


CASES = [
    Case("truncated-laz", "a LAZ file cut in half", _unit(lambda r: _truncate(r / "mls" / "west.laz")), 1,
         "truncated"),
    Case("zero-byte-laz", "a 0-byte .laz in the MLS folder", _unit(lambda r: (r / "mls" / "empty.laz").write_bytes(b"")),
         1, "the campus is incomplete"),
    Case("garbage-laz", "a .laz that is not a LAZ file",
         _unit(lambda r: (r / "mls" / "junk.laz").write_bytes(b"\x00junk" * 500)), 1, "the campus is incomplete"),
    Case("stray-file", "a readme.txt and a .DS_Store in the MLS folder",
         _unit(lambda r: ((r / "mls" / "readme.txt").write_text("crew notes\n"),
                          (r / "mls" / ".DS_Store").write_bytes(b"\0\0"))), 0, "skipped 2 file(s)"),
    Case("dir-named-laz", "a folder named like a LAZ file in the MLS folder",
         _unit(lambda r: (r / "mls" / "extra.laz").mkdir()), 0, "tiles:"),
    Case("dir-as-input", "a folder named like a LAZ file given as the input",
         _unit(lambda r: ((r / "strips.laz").mkdir(), _set_cfg(r, **{"inputs.points": ["strips.laz"]}))), 2,
         "no points files"),
    Case("missing-input", "an input path that does not exist",
         _unit(lambda r: _set_cfg(r, **{"inputs.points": ["mls", "mls-day2"]})), 2, "does not exist"),
    Case("missing-mtl", "an OBJ whose material library is missing", _unit(lambda r: _textured(r, "mtl")), 1,
         "not found"),
    Case("missing-texture", "an OBJ whose texture image is missing", _unit(lambda r: _textured(r, "texture")), 1,
         "not found"),
    Case("nan-vertex", "a mesh with a NaN vertex", _unit(lambda r: _obj_edit(r, "middle.obj", _nan_vertex)), 1,
         "NaN"),
    Case("bad-index", "a face index beyond the vertex list", _unit(lambda r: _obj_edit(r, "east.obj", _bad_index)),
         1, "out of range"),
    Case("empty-mesh", "a mesh file with no faces", _unit(_empty_mesh), 1, "incomplete"),
    Case("degenerate-faces", "repeated-vertex and duplicate faces", _unit(_degenerate_faces), 0, "tiles:"),
    Case("corrupt-glb", "a GLB that is not a glTF binary", _unit(_corrupt_glb), 1, "incomplete"),
    Case("nan-points", "a PLY cloud with NaN coordinates", _unit(_points_nan_ply), 1, "failed"),
    Case("geographic-crs", "a geographic CRS (degrees)", _unit(_geographic), 2, "geographic"),
    Case("wrong-zone", "a CRS that disagrees with the LAS headers (wrong UTM zone)", _unit(_wrong_zone), 2,
         "disagrees"),
    Case("mesh-10km-off", "the mesh 10 km off (wrong mesh_offset)", _unit(_mesh_10km_off), 2, "do not overlap"),
    Case("no-overlap", "MLS strips of another site", _unit(_no_overlap), 2, "do not overlap"),
    Case("wrong-units", "metre data declared as US feet", _unit(_feet), 2, "do not overlap"),
    Case("labels-missing", "a labels file that does not exist", _unit(_labels_missing), 2, "labels file not found"),
    Case("config-typo", "a typo in a config key", _unit(lambda r: _set_cfg(r, **{"tiling.tile_sise_m": 50})), 2,
         "did you mean 'tile_size_m'"),
    Case("broken-yaml", "a YAML syntax error",
         _unit(lambda r: (r / "campus.yaml").write_text((r / "campus.yaml").read_text() + "inputs: [oops\n")), 2,
         "not valid YAML"),
    Case("negative-size", "a negative patch size", _unit(lambda r: _set_cfg(r, **{"partition.patch_size_m": [-2.3, 1, 0.7]})),
         2, "patch sizes must be positive"),
    Case("read-only-workdir", "a read-only work dir", _read_only, 2, "not writable"),
    Case("full-disk", "the disk fills while a new strip is processed", lambda r: ["FULL_DISK"], 1, "no space left"),
]


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
    _set_cfg(root, work_dir="work", runner="inline")
    if not LATER_STAGES:
        _set_cfg(root, **{"classify.enabled": False, "repair.enabled": False, "report.enabled": False})
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
    from storage.patch_store import PatchStore

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
                from storage.pointcloud_io import read_points, write_points

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
