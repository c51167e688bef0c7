"""Checks of an export: tileset.json structure, EXT_mesh_features content, and the Khronos glTF Validator.

No 3D Tiles validator is installable here, so ``check_tileset`` checks in Python what one would: required
keys, ``geometricError`` never increasing from parent to child, every bounding volume enclosing its
content (the glb's vertices, y-up rotated to z-up) and its children's volumes, every content URI present.
An implicit tileset is expanded first (:func:`tasks.export.implicit.expand_implicit`: subtrees readable,
availability consistent), its tiles checked with their tile metadata's boxes and errors, and each content's
mean vertex must lie in the box implicit tiling derives for its tile (coordinates mapped right).
The Khronos validator does not know EXT_mesh_features / EXT_structural_metadata, so ``check_mesh_features``
checks those. ``validate_glbs`` runs ``viewer/validate.mjs`` (npm ``gltf-validator``) with node.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np

from storage.errors import InputError
from tasks.export.georef import gltf_to_enu
from tasks.export.gltf import glb_positions, glb_primitives, read_glb
from tasks.export.implicit import expand_implicit

VIEWER_DIR = Path(__file__).resolve().parents[2] / "viewer"
REQUIRED_TILE_KEYS = ("boundingVolume", "geometricError")


def box_corners(box) -> np.ndarray:
    """(8, 3) corners of a 3D Tiles ``box`` (centre + three half-axis vectors)."""
    b = np.asarray(box, np.float64)
    c, axes = b[:3], b[3:].reshape(3, 3)
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], np.float64)
    return c + signs @ axes


def points_in_box(box, points: np.ndarray, tol_m: float = 1e-4) -> np.ndarray:
    """(n,) bool: which (n, 3) points lie inside ``box`` (any orientation), with ``tol_m`` slack."""
    b = np.asarray(box, np.float64)
    c, axes = b[:3], b[3:].reshape(3, 3)
    half = np.linalg.norm(axes, axis=1)
    unit = axes / np.where(half > 0, half, 1.0)[:, None]
    local = np.abs((np.asarray(points, np.float64) - c) @ unit.T)
    return (local <= half + tol_m).all(axis=1)


def check_tileset(output_dir: str | Path, read_content: bool = True) -> list[str]:
    """Problems found in ``output_dir/tileset.json`` (empty list: it passes). See the module docstring."""
    out = Path(output_dir)
    problems: list[str] = []
    path = out / "tileset.json"
    if not path.is_file():
        return [f"{path}: missing"]
    doc = json.loads(path.read_text())
    if isinstance(doc.get("root"), dict) and "implicitTiling" in doc["root"]:
        try:  # the implicit tiles, with their tile metadata's boxes and errors, checked as explicit ones
            doc = expand_implicit(doc, lambda rel: (out / rel).read_bytes())
        except (InputError, OSError) as e:
            return [f"implicit tiling: {e}"]
    if doc.get("asset", {}).get("version") not in ("1.0", "1.1"):
        problems.append("asset.version missing or not 1.0/1.1")
    if not isinstance(doc.get("geometricError"), (int, float)):
        problems.append("tileset geometricError missing")
    root = doc.get("root")
    if not isinstance(root, dict):
        return problems + ["root missing"]
    if root.get("refine") not in ("ADD", "REPLACE"):
        problems.append("root.refine missing")
    if isinstance(doc.get("geometricError"), (int, float)) and doc["geometricError"] < root.get("geometricError", 0):
        problems.append("tileset geometricError below the root's")
    if "transform" in root and len(root["transform"]) != 16:
        problems.append("root.transform is not 16 numbers")

    def visit(tile: dict, where: str, parent: dict | None) -> None:
        for k in REQUIRED_TILE_KEYS:
            if k not in tile:
                problems.append(f"{where}: {k} missing")
                return
        if where != "root" and "transform" in tile:
            problems.append(f"{where}: nested transforms are not expected in an ms3d tileset")
        box = tile["boundingVolume"].get("box")
        if box is None or len(box) != 12:
            problems.append(f"{where}: boundingVolume.box missing or not 12 numbers")
            return
        if tile["geometricError"] < 0:
            problems.append(f"{where}: negative geometricError")
        if parent is not None:
            if tile["geometricError"] > parent["geometricError"]:
                problems.append(f"{where}: geometricError {tile['geometricError']} exceeds its parent's "
                                f"{parent['geometricError']}")
            outside = ~points_in_box(parent["boundingVolume"]["box"], box_corners(box))
            if outside.any():
                problems.append(f"{where}: bounding box not enclosed by its parent's")
        uri = tile.get("content", {}).get("uri")
        if uri is not None:
            content = out / uri
            if not content.is_file():
                problems.append(f"{where}: content {uri} missing")
            elif read_content:
                pos = gltf_to_enu(glb_positions(content.read_bytes()))
                outside = ~points_in_box(box, pos)
                if outside.any():
                    problems.append(f"{where}: {int(outside.sum())} vertices of {uri} outside its bounding box")
                if "implicit" in tile and len(pos) and not points_in_box(tile["implicit"]["box"], pos.mean(axis=0)[None])[0]:
                    problems.append(f"{where}: {uri} lies outside the box implicit tiling derives for "
                                    f"{tuple(tile['implicit']['coord'])}")
        for i, child in enumerate(tile.get("children", [])):
            visit(child, f"{where}.children[{i}]", tile)

    visit(root, "root", None)
    return problems


def check_mesh_features(data: bytes) -> list[str]:
    """Problems with a glb's EXT_mesh_features / EXT_structural_metadata (empty list: it passes):
    property table arrays of the right length and 8-byte aligned, enum values in their enum, every
    feature id below the table's count, featureCount right, and each triangle within one feature."""
    doc, binary = read_glb(data)
    problems = []
    meta = doc.get("extensions", {}).get("EXT_structural_metadata")
    if meta is None:
        return ["EXT_structural_metadata missing"]
    schema = meta["schema"]
    tables = meta.get("propertyTables", [])
    sizes = {"INT8": 1, "UINT8": 1, "INT16": 2, "UINT16": 2, "INT32": 4, "UINT32": 4, "FLOAT32": 4}
    for t, table in enumerate(tables):
        cls = schema["classes"][table["class"]]
        for name, prop in table["properties"].items():
            spec = cls["properties"][name]
            ctype = schema["enums"][spec["enumType"]]["valueType"] if spec["type"] == "ENUM" else spec["componentType"]
            bv = doc["bufferViews"][prop["values"]]
            if bv["byteOffset"] % 8:
                problems.append(f"table {t}.{name}: bufferView not 8-byte aligned")
            if bv["byteLength"] != sizes[ctype] * table["count"]:
                problems.append(f"table {t}.{name}: {bv['byteLength']} bytes for {table['count']} {ctype} values")
            if spec["type"] == "ENUM":
                vals = np.frombuffer(binary, np.dtype(ctype.lower()), table["count"], bv["byteOffset"])
                allowed = {v["value"] for v in schema["enums"][spec["enumType"]]["values"]}
                if not set(vals.tolist()) <= allowed:
                    problems.append(f"table {t}.{name}: values outside enum {spec['enumType']}")
    prims = doc["meshes"][0]["primitives"]
    for p, (prim, arrays) in enumerate(zip(prims, glb_primitives(data))):
        ext = prim.get("extensions", {}).get("EXT_mesh_features")
        if ext is None:
            problems.append(f"primitive {p}: EXT_mesh_features missing")
            continue
        fids = ext["featureIds"][0]
        ids = arrays.get(f"_FEATURE_ID_{fids['attribute']}")
        if ids is None:
            problems.append(f"primitive {p}: _FEATURE_ID_{fids['attribute']} missing")
            continue
        ids = np.asarray(ids).reshape(-1)
        count = tables[fids["propertyTable"]]["count"]
        if len(ids) and ids.max() >= count:
            problems.append(f"primitive {p}: feature id {int(ids.max())} >= property table count {count}")
        if fids["featureCount"] != len(np.unique(ids)):
            problems.append(f"primitive {p}: featureCount {fids['featureCount']} != {len(np.unique(ids))} distinct ids")
        tri = ids[arrays["indices"]]
        if (tri != tri[:, :1]).any():
            problems.append(f"primitive {p}: {int((tri != tri[:, :1]).any(axis=1).sum())} triangles span features")
    return problems


def node_tools() -> tuple[str | None, str]:
    """(path of node or None, reason when None): node and viewer/node_modules/gltf-validator."""
    node = shutil.which("node")
    if node is None:
        return None, "node is not installed (apt-get install -y nodejs npm)"
    if not (VIEWER_DIR / "node_modules" / "gltf-validator").is_dir():
        return None, "viewer/node_modules missing (npm ci --prefix viewer)"
    return node, ""


def validate_glbs(paths: list[str | Path], batch: int = 64) -> list[dict]:
    """Khronos glTF Validator reports, one dict per file: path, errors, warnings, infos, hints, messages."""
    node, reason = node_tools()
    if node is None:
        raise RuntimeError(reason)
    reports = []
    for lo in range(0, len(paths), batch):
        chunk = [str(p) for p in paths[lo : lo + batch]]
        run = subprocess.run([node, str(VIEWER_DIR / "validate.mjs"), *chunk], capture_output=True, text=True,
                             timeout=600, check=False)  # fmt: skip
        if run.returncode != 0:
            raise RuntimeError(f"validate.mjs failed ({run.returncode}): {run.stderr.strip()[-2000:]}")
        reports.extend(json.loads(run.stdout))
    return reports


def leaf_glbs(out: Path) -> dict[str, Path]:
    """{ground tile: its leaf glb} of an export (explicit or implicit: from the export's node records)."""
    state = out / "tileset.fingerprints.json"
    if state.exists():
        nodes = json.loads(state.read_text()).get("nodes", {})
        return {r["tile"]: out / r["uri"] for r in nodes.values() if r.get("tile")}
    return {p.stem: p for p in sorted((out / "content" / "tiles").glob("*.glb"))}


def ecef_round_trip_error_m(work_dir: str | Path, tile: str, glb: Path | None = None) -> float:
    """Max distance (metres) between the vertices of a leaf glb (default ``content/tiles/{tile}.glb``) taken
    through the tileset's transforms (glTF y-up -> z-up, root ENU->ECEF) and their ECEF positions computed by
    pyproj straight from the projected world coordinates of the tile's merged mesh (matched by nearest
    neighbour)."""
    from pyproj import CRS, Transformer
    from scipy.spatial import cKDTree

    from storage.contracts.tile_mesh import read_tile_mesh
    from storage.frame import CampusFrame

    root = Path(work_dir)
    frame = CampusFrame.from_json(json.loads((root / "campus.json").read_text())["frame"])
    doc = json.loads((root / "output" / "tileset.json").read_text())
    m = np.asarray(doc["root"]["transform"], np.float64).reshape(4, 4).T
    glb = glb or root / "output" / "content" / "tiles" / f"{tile}.glb"
    via = gltf_to_enu(glb_positions(glb.read_bytes()))
    via = via @ m[:3, :3].T + m[:3, 3]
    src = CRS(frame.crs)
    src = src if src.is_compound else src.to_3d()
    world = read_tile_mesh(root / "tiles" / tile).vertices.astype(np.float64) + frame.origin_array
    direct = np.stack(Transformer.from_crs(src, "EPSG:4978", always_xy=True).transform(*world.T), axis=1)
    return float(cKDTree(direct).query(via)[0].max())


def main(argv: list[str] | None = None) -> int:
    """``python -m tasks.export.check WORKDIR``: tileset check, glTF Validator counts, ECEF round trip."""
    import sys

    work = Path((argv if argv is not None else sys.argv[1:])[0])
    out = work / "output"
    problems = check_tileset(out)
    glbs = sorted(out.rglob("*.glb"))
    feature_problems = {str(g): p for g in glbs if g.parent != out / "points"  # the overlay has no faces
                        and (p := check_mesh_features(g.read_bytes()))}
    node, reason = node_tools()
    reports = validate_glbs(glbs) if node else []
    errors_m = [ecef_round_trip_error_m(work, t, g) for t, g in sorted(leaf_glbs(out).items())]
    print(json.dumps({
        "tileset_problems": problems, "glbs": len(glbs), "mesh_feature_problems": feature_problems,
        "validator": ({"errors": sum(r["errors"] for r in reports), "warnings": sum(r["warnings"] for r in reports),
                       "infos": sum(r["infos"] for r in reports)} if node else f"skipped: {reason}"),
        "ecef_round_trip_max_mm": 1000 * max(errors_m) if errors_m else None,
    }, indent=1))  # fmt: skip
    ok = not problems and not feature_problems and (not reports or not any(r["errors"] for r in reports))
    return 0 if ok and (not errors_m or max(errors_m) < 1e-3) else 1


if __name__ == "__main__":
    raise SystemExit(main())
