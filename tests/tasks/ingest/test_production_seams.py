"""A tiled ContextCapture production reads to the same campus-frame mesh as the untiled one: placed by its
metadata.xml, the finest LOD only, and the tile seams welded (coincident border vertices share one id)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh

from storage.errors import InputError
from storage.formats.meshes import read_mesh
from storage.formats.obj import write_obj
from storage.inputs.identity import assign_source_ids, discover
from tasks.config import CampusConfig
from tasks.ingest.kernels import SEAM_ID_BIT, open_boundary_vertices, vertex_ids, weld_vertex_index
from tasks.scan import mesh_placement
from tasks.scan.placement import check_productions

SRS_ORIGIN = np.array([589_000.0, 2_712_000.0, 15.0])
XML = ('<?xml version="1.0" encoding="utf-8"?><ModelMetadata version="1"><SRS>{srs}</SRS>'
       "<SRSOrigin>589000,2712000,15</SRSOrigin><Texture><ColorSource>Visible</ColorSource></Texture>"
       "</ModelMetadata>")


def box_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A closed box 12 x 8 x 5 m, subdivided to 0.75-1.5 m triangles, in world metres (float64)."""
    m = trimesh.creation.box(extents=(12.0, 8.0, 5.0))
    for _ in range(3):
        m = m.subdivide()
    return np.asarray(m.vertices) + [589_050.123, 2_712_030.456, 20.5], np.asarray(m.faces, np.int64)


def write_production(root: Path, srs: str = "EPSG:32650", metadata: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The box cut into 2 x 2 tiles by face centroid, as Data/Tile_+00i_+00j/ OBJ files in coordinates
    local to SRSOrigin; tile (0, 0) also has a coarser level L17 (one triangle) beside its L18."""
    vertices, faces = box_mesh()
    c = vertices[faces].mean(axis=1)
    mid = vertices.mean(axis=0)
    for ix in range(2):
        for iy in range(2):
            sel = faces[((c[:, 0] >= mid[0]) == bool(ix)) & ((c[:, 1] >= mid[1]) == bool(iy))]
            used, f = np.unique(sel, return_inverse=True)
            name = f"Tile_+{ix:03d}_+{iy:03d}"
            stem = f"{name}_L18" if (ix, iy) == (0, 0) else name
            write_obj(root / "Data" / name / f"{stem}.obj", vertices[used], f.reshape(-1, 3), offset=SRS_ORIGIN)
    write_obj(root / "Data" / "Tile_+000_+000" / "Tile_+000_+000_L17.obj", vertices[:3], np.array([[0, 1, 2]]),
              offset=SRS_ORIGIN)
    if metadata:
        (root / "metadata.xml").write_text(XML.format(srs=srs))
    return vertices, faces


def mesh_files(entry: Path) -> tuple[str, ...]:
    """The mesh files a config naming ``entry`` reads (a stand-in point file beside it)."""
    pts = entry.parent / "p.las"
    pts.touch()
    return discover([str(entry)], [str(pts)]).meshes


def cfg_for(mesh: Path, **inputs) -> CampusConfig:
    return CampusConfig.model_validate({"inputs": {"mesh": [str(mesh)], "points": ["mls"], **inputs}})


def read_like_ingest(entry: Path, cfg: CampusConfig, seams: bool = True):
    """The discovered mesh files read and given vertex ids as the scan and ingest stages do: (corners
    (m, 3, 3) float64 world metres, vids (m, 3) int64, file names)."""
    paths = list(mesh_files(entry))
    ids = assign_source_ids(paths)
    tris, vids = [], []
    for p in paths:
        place = mesh_placement(p, cfg)
        mesh = read_mesh(p, offset=place.offset)
        key = place.seam_key if seams else None
        vids.append(vertex_ids(ids[p], mesh.faces, weld_vertex_index(mesh.vertices), mesh.vertices, key))
        tris.append(mesh.vertices[mesh.faces])
    return np.concatenate(tris), np.concatenate(vids), [Path(p).name for p in paths]


def open_edges(vids: np.ndarray) -> int:
    e = np.sort(np.concatenate([vids[:, [0, 1]], vids[:, [1, 2]], vids[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum())


def canonical_faces(tri: np.ndarray) -> np.ndarray:
    """Faces as sorted rows of their corners (order-free comparison of two meshes)."""
    t = np.round(tri, 6).reshape(len(tri), 9)
    return t[np.lexsort(t.T[::-1])]


def test_tiled_production_reads_as_the_untiled_mesh(tmp_path):
    vertices, faces = write_production(tmp_path / "prod")
    write_obj(tmp_path / "single" / "box.obj", vertices, faces, offset=SRS_ORIGIN)

    tri_t, vid_t, names = read_like_ingest(tmp_path / "prod", cfg_for(tmp_path / "prod"))
    tri_s, vid_s, _ = read_like_ingest(tmp_path / "single" / "box.obj",
                                       cfg_for(tmp_path / "single", mesh_offset=SRS_ORIGIN.tolist()))
    assert "Tile_+000_+000_L17.obj" not in names and len(names) == 4  # finest LOD only
    assert len(tri_t) == len(tri_s) == len(faces)
    np.testing.assert_array_equal(canonical_faces(tri_t), canonical_faces(tri_s))  # same place, SRSOrigin added
    n_vertices = len(np.unique(weld_vertex_index(vertices)))
    assert len(np.unique(vid_s)) == len(np.unique(vid_t)) == n_vertices  # seam vertices not doubled
    assert open_edges(vid_s) == open_edges(vid_t) == 0  # the box is closed: no seam is a hole

    _, vid_plain, _ = read_like_ingest(tmp_path / "prod", cfg_for(tmp_path / "prod"), seams=False)
    assert open_edges(vid_plain) > 0 and len(np.unique(vid_plain)) > n_vertices  # what seams did before


def test_seam_ids_only_on_tile_borders_and_never_ordinary(tmp_path):
    write_production(tmp_path / "prod")
    _, vids, _ = read_like_ingest(tmp_path / "prod", cfg_for(tmp_path / "prod"))
    seam = (vids & SEAM_ID_BIT) != 0
    assert (vids >= 0).all() and 0 < seam.mean() < 0.5
    ordinary = vids[~seam]
    assert ((ordinary & 0xFFFFFFFF) < SEAM_ID_BIT).all()


def test_ordinary_file_ids_are_unchanged():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    assert vertex_ids(9, f, weld_vertex_index(v)).tolist() == [[(9 << 32) | i for i in r] for r in f.tolist()]
    assert open_boundary_vertices(f, np.arange(4)).all()


def test_metadata_places_the_production_and_must_agree_with_the_config(tmp_path):
    write_production(tmp_path / "prod")
    tile = next((tmp_path / "prod" / "Data" / "Tile_+001_+001").glob("*.obj"))
    place = mesh_placement(tile, cfg_for(tmp_path / "prod"))
    assert place.offset == tuple(SRS_ORIGIN) and place.crs == "EPSG:32650" and place.seam_key is not None
    same = cfg_for(tmp_path / "prod", mesh_offset=SRS_ORIGIN.tolist(), crs="EPSG:32650")
    assert mesh_placement(tile, same).offset == tuple(SRS_ORIGIN)
    with pytest.raises(InputError, match="disagrees with inputs.mesh_offset") as e:
        mesh_placement(tile, cfg_for(tmp_path / "prod", mesh_offset=[589_010.0, 2_712_000.0, 15.0]))
    assert "metadata.xml" in str(e.value)
    with pytest.raises(InputError, match="disagrees with the configured inputs.crs"):
        check_productions([str(tile)], cfg_for(tmp_path / "prod", crs="EPSG:32651"))


def test_production_without_metadata_is_refused_unless_placed_by_the_config(tmp_path, caplog):
    write_production(tmp_path / "prod", metadata=False)
    meshes = mesh_files(tmp_path / "prod")
    with pytest.raises(InputError, match="without metadata.xml") as e:
        check_productions(meshes, cfg_for(tmp_path / "prod"))
    assert str(tmp_path / "prod") in str(e.value)
    cfg = cfg_for(tmp_path / "prod", mesh_offset=SRS_ORIGIN.tolist())
    with caplog.at_level(logging.WARNING):
        assert len(check_productions(meshes, cfg)) == 1
    assert "placed by inputs.mesh_offset" in caplog.text
    _, vids, _ = read_like_ingest(tmp_path / "prod", cfg)
    assert open_edges(vids) == 0  # still a production: its seams weld


def test_unknown_srs_is_refused_before_anything_is_read(tmp_path):
    write_production(tmp_path / "prod", srs="Local")
    meshes = mesh_files(tmp_path / "prod")
    with pytest.raises(InputError, match="unknown SRS 'Local'"):
        check_productions(meshes, cfg_for(tmp_path / "prod"))


def _enu_production(root: Path) -> np.ndarray:
    """A single-file production in a local ENU frame at (24.51 N, 117.65 E), SRSOrigin (10, 20, 5): four
    vertices at the origin, 100 m east, 100 m north and 10 m up of it (file coordinates)."""
    v = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 10.0]])
    write_obj(root / "m.obj", v, np.array([[0, 1, 2], [0, 1, 3]]))
    (root / "metadata.xml").write_text('<ModelMetadata version="1"><SRS>ENU:24.51,117.65</SRS>'
                                       "<SRSOrigin>10,20,5</SRSOrigin></ModelMetadata>")
    return v


def test_enu_production_is_placed_into_the_campus_crs(tmp_path):
    """ENU -> ECEF -> UTM: the tangent point lands where PROJ puts (24.51 N, 117.65 E); distances keep the
    UTM scale factor; the east axis turns by the grid convergence; up stays up."""
    from pyproj import Proj, Transformer

    from tasks.scan import place_mesh

    _enu_production(tmp_path / "enu")
    with pytest.raises(InputError, match="local frame .*set inputs.crs"):
        mesh_placement(tmp_path / "enu" / "m.obj", cfg_for(tmp_path / "enu"))
    cfg = cfg_for(tmp_path / "enu", crs="EPSG:32650")
    place = mesh_placement(tmp_path / "enu" / "m.obj", cfg)
    assert place.crs == "EPSG:32650" and place.enu == (24.51, 117.65) and place.to_json()["enu"] == [24.51, 117.65]
    v = place_mesh(read_mesh(tmp_path / "enu" / "m.obj", offset=place.offset), place).vertices
    x0, y0 = Transformer.from_crs("EPSG:4326", "EPSG:32650", always_xy=True).transform(117.65, 24.51)
    # the file's origin is SRSOrigin (10, 20, 5) from the tangent point
    k = Proj("EPSG:32650").get_factors(117.65, 24.51)
    o = v[0] - [x0, y0, 0.0]
    assert np.hypot(*o[:2]) == pytest.approx(np.hypot(10, 20) * k.meridional_scale, abs=2e-3)
    assert o[2] == pytest.approx(5.0, abs=1e-3)
    east, north, up = v[1] - v[0], v[2] - v[0], v[3] - v[0]
    assert np.hypot(*east[:2]) == pytest.approx(100 * k.meridional_scale, abs=2e-3)
    assert np.hypot(*north[:2]) == pytest.approx(100 * k.meridional_scale, abs=2e-3)
    turn = np.degrees(np.arctan2(east[1], east[0]))
    assert abs(turn) == pytest.approx(abs(k.meridian_convergence), abs=0.01) and abs(turn) > 0.2
    assert up[2] == pytest.approx(10.0, abs=1e-3) and np.hypot(*up[:2]) < 1e-3
    # a map-CRS production's placement keeps its fingerprint: no "enu" key
    write_production(tmp_path / "prod")
    assert "enu" not in mesh_placement(mesh_files(tmp_path / "prod")[0], cfg_for(tmp_path / "prod")).to_json()