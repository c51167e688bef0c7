"""The cases of ``benchmarks/bad_inputs.py``: each breaks one thing in a good campus folder (``synth.handmade``:
three regions ``west``, ``middle``, ``east``, each with a mesh and a LAZ file) and says what ``ms3d run``
must answer."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml


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


def set_cfg(root: Path, **changes) -> None:
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
    set_cfg(root, **{"inputs.crs": "EPSG:4326"})


def _wrong_zone(root: Path) -> None:
    set_cfg(root, **{"inputs.crs": "EPSG:32651"})  # the LAS headers say EPSG:32650


def _mesh_10km_off(root: Path) -> None:
    o = _cfg(root)["inputs"]["mesh_offset"]
    set_cfg(root, **{"inputs.mesh_offset": [o[0] + 10_000.0, o[1], o[2]]})


def _no_overlap(root: Path) -> None:
    from storage.formats.points import read_points, write_points

    for p in (root / "mls").glob("*.laz"):
        pc = read_points(p)
        pc.xyz = pc.xyz + [0.0, 3_000.0, 0.0]
        write_points(p, pc, crs="EPSG:32650")


def _feet(root: Path) -> None:
    set_cfg(root, **{"inputs.units_scale": 0.3048})  # metres declared as US feet


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
    set_cfg(root, **{"inputs.labels": "truth/missing.json"})


def _degenerate_faces(root: Path) -> None:
    def edit(lines):
        return lines + ["f 1 1 2", "f 3 4 3", "f 1 2 3", "f 1 2 3"]  # repeated ids, duplicates: dropped, counted
    _obj_edit(root, "middle.obj", edit)


def _broken_cameras(root: Path) -> None:
    """A COLMAP text model whose images.txt was cut mid-line (a copy interrupted)."""
    from storage.formats.camera_files import write_colmap
    from storage.formats.cameras import Camera

    cam = Camera("IMG_0001.JPG", np.array([[1000.0, 0, 511.5], [0, 1000.0, 383.5], [0, 0, 1]]), np.eye(3),
                 np.zeros(3), 1024, 768, np.array([-0.1, 0.01, 0.0, 0.0, 0.0]))
    write_colmap(root / "sparse", [cam, cam])
    p = root / "sparse" / "images.txt"
    p.write_text(p.read_text()[:-30])
    set_cfg(root, **{"inputs.cameras": "sparse"})


def _as_production(root: Path, srs: str | None) -> None:
    """Move each mesh into a ContextCapture tile folder (mesh/Data/Tile_+00k_+000/); with ``srs``, write
    mesh/metadata.xml placing it at the configured mesh_offset (then removed from the config)."""
    o = _cfg(root)["inputs"]["mesh_offset"]
    for k, p in enumerate(sorted((root / "mesh").glob("*.obj"))):
        name = f"Tile_+{k:03d}_+000"
        (root / "mesh" / "Data" / name).mkdir(parents=True)
        p.rename(root / "mesh" / "Data" / name / f"{name}.obj")
    if srs is not None:
        (root / "mesh" / "metadata.xml").write_text(
            f'<?xml version="1.0" encoding="utf-8"?><ModelMetadata version="1"><SRS>{srs}</SRS>'
            f"<SRSOrigin>{o[0]!r},{o[1]!r},{o[2]!r}</SRSOrigin></ModelMetadata>")
    set_cfg(root, **{"inputs.mesh_offset": [0.0, 0.0, 0.0]})


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
         _unit(lambda r: ((r / "strips.laz").mkdir(), set_cfg(r, **{"inputs.points": ["strips.laz"]}))), 2,
         "no points files"),
    Case("missing-input", "an input path that does not exist",
         _unit(lambda r: set_cfg(r, **{"inputs.points": ["mls", "mls-day2"]})), 2, "does not exist"),
    Case("missing-mtl", "an OBJ whose material library is missing (read untextured, one warning)",
         _unit(lambda r: _textured(r, "mtl")), 0, "middle.mtl (mtllib) not found"),
    Case("missing-texture", "an OBJ whose texture image is missing (read untextured, one warning)",
         _unit(lambda r: _textured(r, "texture")), 0, "facade.jpg (map_Kd) not found"),
    Case("nan-vertex", "a mesh with a NaN vertex (its faces dropped, one warning)",
         _unit(lambda r: _obj_edit(r, "middle.obj", _nan_vertex)), 0, "touch NaN or infinite vertices"),
    Case("bad-index", "a face index beyond the vertex list (that face dropped, one warning)",
         _unit(lambda r: _obj_edit(r, "east.obj", _bad_index)), 0, "dropped 1 of"),
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
    Case("production-no-metadata", "a tiled production without metadata.xml (and no mesh_offset)",
         _unit(lambda r: _as_production(r, None)), 2, "without metadata.xml"),
    Case("production-unknown-srs", "a production whose metadata.xml has an ENU SRS",
         _unit(lambda r: _as_production(r, "ENU:24.51,117.65")), 2, "unknown SRS"),
    Case("labels-missing", "a labels file that does not exist", _unit(_labels_missing), 2, "labels file not found"),
    Case("broken-cameras", "a camera file cut mid-line (COLMAP images.txt)", _unit(_broken_cameras), 2,
         "images.txt: line 4: expected IMAGE_ID"),
    Case("config-typo", "a typo in a config key", _unit(lambda r: set_cfg(r, **{"tiling.tile_sise_m": 50})), 2,
         "did you mean 'tile_size_m'"),
    Case("broken-yaml", "a YAML syntax error",
         _unit(lambda r: (r / "campus.yaml").write_text((r / "campus.yaml").read_text() + "inputs: [oops\n")), 2,
         "not valid YAML"),
    Case("negative-size", "a negative patch size", _unit(lambda r: set_cfg(r, **{"partition.patch_size_m": [-2.3, 1, 0.7]})),
         2, "patch sizes must be positive"),
    Case("read-only-workdir", "a read-only work dir", _read_only, 2, "not writable"),
    Case("full-disk", "the disk fills while a new strip is processed", lambda r: ["FULL_DISK"], 1, "no space left"),
]
