"""ContextCapture productions: metadata.xml, which files belong to a production, the finest LOD only."""

from __future__ import annotations

from pathlib import Path

import pytest

from storage.errors import InputError
from storage.formats.production import (
    finest_lod,
    production_key,
    production_of,
    production_root,
    read_metadata,
)
from storage.inputs.identity import discover

XML = ('<?xml version="1.0" encoding="utf-8"?><ModelMetadata version="1"><SRS>{srs}</SRS>{origin}'
       "<Texture><ColorSource>Visible</ColorSource></Texture></ModelMetadata>")


def write_metadata(root: Path, srs: str = "EPSG:32650", origin: str | None = "589000,2712000,15") -> Path:
    root.mkdir(parents=True, exist_ok=True)
    p = root / "metadata.xml"
    p.write_text(XML.format(srs=srs, origin=f"<SRSOrigin>{origin}</SRSOrigin>" if origin is not None else ""))
    return p


def test_metadata_gives_srs_and_origin(tmp_path):
    m = read_metadata(write_metadata(tmp_path, "epsg:32650", "589000.5,2712000.25,15"))
    assert (m.srs, m.origin) == ("EPSG:32650", (589000.5, 2712000.25, 15.0))
    assert read_metadata(write_metadata(tmp_path, origin=None)).origin == (0.0, 0.0, 0.0)
    assert read_metadata(write_metadata(tmp_path, "EPSG:32650+5773")).srs == "EPSG:32650+5773"


def test_wkt_and_enu_srs_are_read(tmp_path):
    from pyproj import CRS

    utm = CRS.from_epsg(32650)
    for wkt in (utm.to_wkt("WKT1_GDAL"), utm.to_wkt("WKT2_2019")):
        assert read_metadata(write_metadata(tmp_path, wkt)).srs == "EPSG:32650"
    rd_nap = CRS.from_user_input("EPSG:7415").to_wkt()
    assert read_metadata(write_metadata(tmp_path, rd_nap)).srs == "EPSG:28992+5709"
    m = read_metadata(write_metadata(tmp_path, "ENU:24.51, 117.65", "1,2,3"))
    assert (m.srs, m.enu, m.origin) == ("ENU:24.51,117.65", (24.51, 117.65), (1.0, 2.0, 3.0))


@pytest.mark.parametrize("srs", ['PROJCS["WGS 84 / UTM zone 50N",GEOGCS["WGS 84"]]', "Local", "ENU:95,10",
                                 'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],'
                                 'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]]'])
def test_unknown_srs_is_one_line_naming_the_file(tmp_path, srs):
    p = write_metadata(tmp_path, srs)
    with pytest.raises(InputError, match="unknown SRS") as e:
        read_metadata(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("text, says", [("<ModelMetadata><SRS>EPSG:1", "not a readable XML"),
                                        ("<Other/>", "not a ContextCapture metadata"),
                                        ("<ModelMetadata version='1'/>", "no <SRS>"),
                                        ("<ModelMetadata><SRS>EPSG:32650</SRS><SRSOrigin>1,x,2</SRSOrigin>"
                                         "</ModelMetadata>", "SRSOrigin")])
def test_broken_metadata_names_the_file(tmp_path, text, says):
    p = tmp_path / "metadata.xml"
    p.write_text(text)
    with pytest.raises(InputError, match=says):
        read_metadata(p)


def test_which_files_belong_to_a_production(tmp_path):
    tile = tmp_path / "prod" / "Data" / "Tile_+000_+000" / "Tile_+000_+000.obj"
    assert production_root(tile) == tmp_path / "prod"  # even without metadata.xml (then it is refused later)
    assert production_of(tile).metadata is None
    write_metadata(tmp_path / "prod")
    prod = production_of(tile)
    assert prod.metadata.origin == (589000.0, 2712000.0, 15.0) and prod.key == production_key(tmp_path / "prod")
    assert production_root(tmp_path / "flat" / "Tile_+001_+000" / "Tile_+001_+000_L19.obj") == tmp_path / "flat"
    assert production_root(tmp_path / "site" / "west.obj") is None  # an ordinary file
    write_metadata(tmp_path / "site")
    assert production_root(tmp_path / "site" / "west.obj") == tmp_path / "site"  # a single-file production
    assert production_key(tmp_path / "a") != production_key(tmp_path / "b")


def test_finest_lod_per_tile(tmp_path):
    t0 = [f"/p/Data/Tile_+000_+000/Tile_+000_+000_L{k}.obj" for k in (17, 18)]
    t1 = [f"/p/Data/Tile_+001_+000/Tile_+001_+000_L{k}_{s}.obj" for k, s in ((18, 0), (19, 0), (19, 1))]
    plain = ["/p/Data/Tile_+002_+000/Tile_+002_+000.obj", "/p/building_L2.obj"]
    kept, skipped = finest_lod(t0 + t1 + plain)
    assert kept == sorted([t0[1], t1[1], t1[2]] + plain)
    assert [p for p, _ in skipped] == sorted([t0[0], t1[0]])
    assert "L17 of Tile_+000_+000: only the finest, L18" in dict(skipped)[t0[0]]


def test_discovery_of_a_production_folder_keeps_the_finest_level(tmp_path):
    root = tmp_path / "prod"
    write_metadata(root)
    for name in ("Tile_+000_+000_L18", "Tile_+000_+000_L19"):
        (root / "Data" / "Tile_+000_+000").mkdir(parents=True, exist_ok=True)
        (root / "Data" / "Tile_+000_+000" / f"{name}.obj").write_text("v 0 0 0\n")
        (root / "Data" / "Tile_+000_+000" / f"{name}.mtl").write_text("")
    (tmp_path / "a.las").write_bytes(b"")
    found = discover([str(root)], [str(tmp_path / "a.las")])
    assert [Path(p).name for p in found.meshes] == ["Tile_+000_+000_L19.obj"]
    assert [(Path(p).name, "L18" in why) for p, why in found.skipped] == [("Tile_+000_+000_L18.obj", True)]


def test_a_mesh_folder_reads_only_the_finest_level(tmp_path):
    """Readers of a whole mesh folder (the quality stage's input-mesh row) take what discovery takes."""
    from storage.formats.meshes import mesh_files

    for name in ("Tile_+000_+000_L17.obj", "Tile_+000_+000_L18.obj"):
        d = tmp_path / "Data" / "Tile_+000_+000"
        d.mkdir(parents=True, exist_ok=True)
        (d / name).write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert [p.name for p in mesh_files(tmp_path)] == ["Tile_+000_+000_L18.obj"]
