"""ContextCapture / iTwin Capture Modeler productions: ``metadata.xml`` and which tile files to read.

A production in OBJ is a folder like::

    production/metadata.xml                        SRS and SRSOrigin of the whole production
    production/Data/Tile_+000_+000/Tile_+000_+000.obj        one level (+ .mtl and textures)
    production/Data/Tile_+001_+000/Tile_+001_+000_L18.obj    or several levels of detail,
    production/Data/Tile_+001_+000/Tile_+001_+000_L19.obj    of which only the finest (highest L) is read

and ``metadata.xml`` reads::

    <ModelMetadata version="1"><SRS>EPSG:32650</SRS><SRSOrigin>589000,2712000,15</SRSOrigin>...</ModelMetadata>

The OBJ coordinates are metres from SRSOrigin, in the SRS. ms3d reads ``EPSG:<code>`` SRSs (optionally
compound, ``EPSG:32650+5773``), a projected WKT that identifies with an EPSG code, and ``ENU:<lat>,<lon>``
local frames, placed into ``inputs.crs`` (:mod:`storage.formats.srs`); any other SRS is refused with one
line naming the file ("unknown SRS ...").

Which files belong to a production is decided from the file's own path (so each ingest unit, which sees
one file, knows it): a file in a ``Tile_*`` folder is a tile of the production rooted at that folder's
parent (or at the parent of ``Data/``), whether or not that root holds ``metadata.xml``; any other mesh
file is a (single-file) production when ``metadata.xml`` sits beside it.
"""

from __future__ import annotations

import hashlib
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from storage.errors import InputError
from storage.formats.srs import parse_srs
from storage.inputs.location import Location

METADATA_NAME = "metadata.xml"
TILE_PREFIX = "Tile_"
_LOD = re.compile(r"^(?P<tile>.+?)_L(?P<level>\d+)(?:_\d+)?$")  # Tile_+000_+000_L19 or _L19_01 (a subtile)


@dataclass(frozen=True)
class ProductionMetadata:
    """What ``metadata.xml`` says. path: absolute; srs: "EPSG:<code>[+<code>]" or "ENU:<lat>,<lon>";
    origin: SRSOrigin, float64 metres in the SRS, added to the OBJ coordinates ((0, 0, 0) when the file has
    no SRSOrigin); enu: (lat, lon) degrees of a local ENU frame's tangent point, None for a map CRS."""

    path: str
    srs: str
    origin: tuple[float, float, float]
    enu: tuple[float, float] | None = None


@dataclass(frozen=True)
class Production:
    """The production a mesh file belongs to. root: absolute folder; metadata: None when the root has no
    ``metadata.xml``; key: stable 64-bit id of the root (from its absolute path), which keys the vertex
    ids of its tile seams."""

    root: str
    metadata: ProductionMetadata | None
    key: int

    @property
    def metadata_path(self) -> Path:
        return Path(self.root) / METADATA_NAME


def read_metadata(path: str | Path) -> ProductionMetadata:
    """Parse a ContextCapture ``metadata.xml``. Raises InputError naming the file when it is not valid
    XML, not a ``ModelMetadata``, has no SRS or one it cannot use (:func:`storage.formats.srs.parse_srs`), or a
    bad SRSOrigin."""
    path = Path(path).absolute()
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise InputError(path, "metadata file not found") from None
    except (ET.ParseError, OSError) as e:
        raise InputError(path, f"not a readable XML file ({e})") from None
    if root.tag != "ModelMetadata":
        raise InputError(path, f"not a ContextCapture metadata file (root element <{root.tag}>, "
                               "expected <ModelMetadata>)")
    srs_text = (root.findtext("SRS") or "").strip()
    if not srs_text:
        raise InputError(path, "no <SRS>: the production cannot be georeferenced")
    srs = parse_srs(srs_text, path)
    text = (root.findtext("SRSOrigin") or "0,0,0").strip()
    try:
        origin = tuple(float(v) for v in text.split(","))
    except ValueError:
        origin = ()
    if len(origin) == 2:
        origin = (*origin, 0.0)
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise InputError(path, f"SRSOrigin {text!r} is not three finite numbers 'x,y,z'")
    return ProductionMetadata(str(path), srs.name, origin, srs.enu)  # type: ignore[arg-type]


def production_key(root: str | Path) -> int:
    """Stable 64-bit id of a production root (SHA-256 of its absolute path), as a Python int < 2**64."""
    return int.from_bytes(hashlib.sha256(str(Path(root).absolute()).encode()).digest()[:8], "big")


def production_root_of(mesh: Location, has_file: Callable[[Location], bool]) -> Location | None:
    """The root of the production a mesh file belongs to (module doc), or None for an ordinary file: the one
    rule, for a local path and a URL alike. It looks only at the path and asks ``has_file`` whether
    ``metadata.xml`` exists beside the file (``Path.is_file`` locally, a HEAD on a bucket)."""
    folder = mesh.parent
    if folder.name.startswith(TILE_PREFIX):
        return folder.parent.parent if folder.parent.name == "Data" else folder.parent
    if has_file(folder / METADATA_NAME):
        return folder
    if folder.name == "Data" and has_file(folder.parent / METADATA_NAME):
        return folder.parent
    return None


def production_root(mesh_path: str | Path) -> Path | None:
    """:func:`production_root_of` a local mesh file (absolute), or None for an ordinary file."""
    root = production_root_of(Location(Path(mesh_path).absolute()), lambda loc: loc.path.is_file())
    return None if root is None else root.path


def scene_production(scene_path: str | Path) -> Production:
    """A 3MX scene file (``.3mx``) as a production: its first mesh layer's SRS and SRSOrigin are the
    metadata (the scene file is the metadata path; :func:`storage.formats.threemx.read_3mx` places further
    layers relative to the first). InputError naming the scene when its SRS is missing or unusable."""
    from storage.formats.threemx import read_scene

    path = Path(scene_path).absolute()
    layer = read_scene(path)[0]
    if not layer.srs.strip():
        raise InputError(path, "the 3MX scene's layer has no SRS: the production cannot be georeferenced")
    srs = parse_srs(layer.srs, path)
    meta = ProductionMetadata(str(path), srs.name, layer.origin, srs.enu)
    return Production(str(path.parent), meta, production_key(path))


def production_of(mesh_path: str | Path) -> Production | None:
    """The :class:`Production` of a mesh file (its metadata read), or None for an ordinary file.
    Raises InputError (naming ``metadata.xml``) when the metadata exists but cannot be used."""
    if Path(mesh_path).suffix.lower() == ".3mx":
        return scene_production(mesh_path)
    root = production_root(mesh_path)
    if root is None:
        return None
    meta_path = root / METADATA_NAME
    meta = read_metadata(meta_path) if meta_path.is_file() else None
    return Production(str(root), meta, production_key(root))


def finest_lod(paths: list[str]) -> tuple[list[str], list[tuple[str, str]]]:
    """Keep, per tile, only the files of its finest level of detail.

    Files named ``Tile_<tile>_L<level>[_<subtile>].<ext>`` in one folder are levels of one tile: those of the
    highest level are kept (all its subtiles), the others are returned as skipped with why. Files
    without a level suffix are a single level and always kept. Returns (kept, sorted; skipped (path, why)).

    >>> kept, skipped = finest_lod(["/p/Tile_0/Tile_0_L18.obj", "/p/Tile_0/Tile_0_L19.obj", "/p/Tile_1/Tile_1.obj"])
    >>> kept, [why for _, why in skipped]
    (['/p/Tile_0/Tile_0_L19.obj', '/p/Tile_1/Tile_1.obj'], ['level of detail L18 of Tile_0: only the finest, L19, is read'])
    """
    levels: dict[tuple[str, str, str], list[tuple[int, str]]] = {}
    kept: list[str] = []
    for p in paths:
        q = Path(p)
        m = _LOD.match(q.stem) if q.stem.startswith(TILE_PREFIX) else None
        if m is None:
            kept.append(p)
        else:
            levels.setdefault((str(q.parent), m["tile"], q.suffix.lower()), []).append((int(m["level"]), p))
    skipped = []
    for (_, tile, _), items in levels.items():
        top = max(level for level, _ in items)
        kept += [p for level, p in items if level == top]
        skipped += [(p, f"level of detail L{level} of {tile}: only the finest, L{top}, is read")
                    for level, p in items if level != top]
    return sorted(kept), sorted(skipped)
