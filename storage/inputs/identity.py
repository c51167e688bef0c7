"""Input files by identity: discovery, stable source ids and content fingerprints.

Everything downstream of the inputs is keyed by *what* a file is (its path and its content), never by
its position in a list: a removed, renamed, reordered, added or shrunk file changes exactly the keys
that depend on it.

- ``source_id(path)``: a stable 31-bit id of a file, from the SHA-256 of its absolute path. It is the
  ``source`` column of the patch store and the high bits of the campus-unique mesh vertex ids
  (``source << 32 | vertex index``). Ids are assigned over the sorted set of paths, and a collision (two
  paths with one hash; ~0.02 % for 1,000 files) moves the later path to the next free id, so the
  assignment is a function of the set of files, the same in every run over that set.
- Folder scans take the supported extensions only and report what they skipped (a ``readme.txt``, a
  hidden or temporary file), so a stray file can never fail a campus.
- A ContextCapture production folder (``metadata.xml``, ``Data/Tile_*/``) is scanned like any folder of
  meshes, but of a tile with levels of detail (``Tile_+000_+000_L18.obj``, ``_L19``, ...) only the finest
  level is taken; the coarser ones are reported as skipped (:mod:`storage.formats.production`).
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

from storage.atomic import file_fingerprint
from storage.errors import InputError
from storage.formats.production import finest_lod
from storage.formats.threemx import select_3mx
from storage.inputs.location import is_url
from storage.inputs.remote import discover_url, url_fingerprint

SOURCE_ID_BITS = 31
VERTEX_INDEX_BITS = 32  # up to 4.29e9 vertices per mesh file

# Extensions a folder scan takes (a .txt or .csv of x y z is read when named explicitly, but in a folder it
# is far more often a readme or a log).
POINT_SUFFIXES = frozenset({".las", ".laz", ".ply", ".pcd", ".xyz", ".pts", ".e57"})
MESH_SUFFIXES = frozenset({".obj", ".ply", ".glb", ".gltf", ".off", ".stl", ".3mx", ".3mxb"})


def _hash_id(path: str) -> int:
    return int.from_bytes(hashlib.sha256(path.encode()).digest()[:8], "big") & ((1 << SOURCE_ID_BITS) - 1)


def assign_source_ids(paths: list[str]) -> dict[str, int]:
    """Stable ids for a set of absolute paths: {path: id}, ids unique, each < 2**31."""
    out: dict[str, int] = {}
    used: set[int] = set()
    for p in sorted(set(paths)):
        i = _hash_id(p)
        while i in used:  # linear probing over the sorted set: deterministic for a given set
            i = (i + 1) & ((1 << SOURCE_ID_BITS) - 1)
        used.add(i)
        out[p] = i
    return out


@dataclass
class InputFile:
    """One input file as scanned (JSON-able; kept in campus.json).

    source: stable id (see module doc); path: absolute; kind: "points" | "mesh"; fingerprint: content
    fingerprint; count: points or faces; lo/hi: world bounds (mesh after offset and units scale), empty
    when unknown; crs: of a LAS header; error: why the file cannot be used ("" when fine); warnings: what
    its reader worked around (``MeshData.warnings``: dropped faces, a missing texture), one line each.
    """

    source: int
    path: str
    kind: str
    fingerprint: str
    count: int = 0
    lo: list[float] = field(default_factory=list)
    hi: list[float] = field(default_factory=list)
    crs: str | None = None
    error: str = ""
    warnings: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return Path(self.path).name

    @property
    def bounded(self) -> bool:
        return bool(self.lo) and bool(self.hi)

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Discovery:
    """The files the config names. meshes/points: absolute paths, sorted; skipped: (path, why)."""

    meshes: tuple[str, ...]
    points: tuple[str, ...]
    skipped: tuple[tuple[str, str], ...] = ()


def _scan_folder(folder: Path, suffixes: frozenset[str], kind: str, skipped: list) -> list[str]:
    found = []
    for p in sorted(folder.rglob("*")):
        if p.is_dir():
            continue
        if p.name.startswith(".") or any(part.startswith(".") for part in p.relative_to(folder).parts[:-1]):
            skipped.append((str(p), "hidden or temporary file"))
        elif p.suffix.lower() in suffixes:
            found.append(str(p.absolute()))
        elif kind == "mesh" and p.suffix.lower() in {".mtl", ".jpg", ".jpeg", ".png", ".xml", ".tif", ".tiff"}:
            continue  # materials, textures and ContextCapture metadata belong with the meshes
        else:
            skipped.append((str(p), f"not a {kind} file (extension {p.suffix or 'none'!r})"))
    return found


def discover(mesh_entries: list[str], point_entries: list[str]) -> Discovery:
    """Expand the config's input entries (files or folders) into files.

    A folder contributes its files with a supported extension (recursively), of a tiled production
    only the finest level of detail; anything else is listed in ``skipped``. A named file is taken whatever its extension (its reader then says if it cannot be
    read). Raises InputError for an entry that does not exist and when no mesh or no point cloud is left.
    """
    skipped: list[tuple[str, str]] = []
    out = {}
    for kind, entries, suffixes in (("mesh", mesh_entries, MESH_SUFFIXES), ("points", point_entries, POINT_SUFFIXES)):
        files: list[str] = []
        for e in entries:
            if is_url(e):  # an input by URL: storage.inputs.remote
                found = discover_url(e, kind, suffixes, skipped)
                if kind == "mesh":
                    found, coarser = finest_lod(found)
                    skipped += coarser
                files += found
                continue
            p = Path(e)
            if p.is_dir():
                found = _scan_folder(p, suffixes, kind, skipped)
                if not found:
                    raise InputError(p, f"no {kind} files ({', '.join(sorted(suffixes))}) in this folder")
                if kind == "mesh":
                    found, levels = select_3mx(found)
                    found, coarser = finest_lod(found)
                    skipped += levels + coarser
                files += found
            elif p.exists():
                files.append(str(p.absolute()))
            else:
                raise InputError(p, f"{kind} input does not exist (inputs.{'mesh' if kind == 'mesh' else 'points'} "
                                    "in the config)")
        out[kind] = tuple(sorted(set(files)))
    if not out["mesh"]:
        raise InputError(None, "no mesh input: set inputs.mesh in the config")
    if not out["points"]:
        raise InputError(None, "no point-cloud input: set inputs.points in the config")
    return Discovery(out["mesh"], out["points"], tuple(skipped))


def fingerprint(path: str | Path) -> str:
    """Content fingerprint of an input file (size, mtime and the first and last MiB); of an input by URL,
    its ETag and size (one HEAD request, :func:`storage.inputs.remote.url_fingerprint`)."""
    if is_url(path):
        return url_fingerprint(path)
    return file_fingerprint(path)
