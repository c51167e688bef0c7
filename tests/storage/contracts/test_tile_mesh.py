"""TileMesh: the merge -> export contract, written and read back."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from storage.contracts.tile_mesh import TileMesh, read_tile_arrays, read_tile_mesh, write_tile_mesh
from storage.errors import InputError


def _mesh(texture: str) -> TileMesh:
    return TileMesh(
        tile="3_-1",
        vertices=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]], np.float32),
        faces=np.array([[0, 1, 2], [1, 3, 2]], np.int32),
        uv=np.array([[0, 0], [1, 0], [0, 1], [1, 1]], np.float32),
        face_texture=np.array([0, -1], np.int16),
        textures=[texture],
        vertex_colors=np.array([[1, 2, 3]] * 4, np.uint8),
        grade=np.array([0, 1], np.int8), source=np.array([0, 1], np.int8), region=np.array([-1, 4], np.int32),
    )  # fmt: skip


def test_round_trip_keeps_every_array_and_relative_textures(tmp_path):
    tex = tmp_path / "regions" / "r000004" / "atlas.png"
    tex.parent.mkdir(parents=True)
    Image.new("RGB", (4, 4)).save(tex)
    tile_dir = tmp_path / "tiles" / "3_-1"
    mesh = _mesh(str(tex))
    write_tile_mesh(tile_dir, mesh)
    assert '"../../regions/r000004/atlas.png"' in (tile_dir / "merged.json").read_text()
    back = read_tile_mesh(tile_dir)
    assert back.tile == "3_-1" and back.textures == [str(tex.resolve())]
    for name in ("vertices", "faces", "uv", "face_texture", "vertex_colors", "grade", "source", "region"):
        got, want = getattr(back, name), getattr(mesh, name)
        assert got.dtype == want.dtype and np.array_equal(got, want), name


def test_contract_violations_are_refused(tmp_path):
    with pytest.raises(ValueError, match="faces must be"):
        TileMesh(**{**_mesh("t.png").__dict__, "faces": np.array([[0, 1, 2]], np.int64)})
    with pytest.raises(ValueError, match="out of range"):
        TileMesh(**{**_mesh("t.png").__dict__, "faces": np.array([[0, 1, 9], [0, 1, 2]], np.int32)})


def test_missing_texture_or_corrupt_file_names_the_file(tmp_path):
    tex = tmp_path / "a.png"
    Image.new("RGB", (4, 4)).save(tex)
    write_tile_mesh(tmp_path / "tiles" / "0_0", _mesh(str(tex)))
    tex.unlink()
    with pytest.raises(InputError, match="a.png not found"):
        read_tile_mesh(tmp_path / "tiles" / "0_0")
    Image.new("RGB", (4, 4)).save(tex)
    (tmp_path / "tiles" / "0_0" / "merged.npz").write_bytes(b"garbage")
    with pytest.raises(InputError, match="merged.npz"):
        read_tile_mesh(tmp_path / "tiles" / "0_0")
    with pytest.raises(InputError, match="run the merge stage"):
        read_tile_mesh(tmp_path / "tiles" / "9_9")


def test_named_arrays_equal_the_full_read_and_bad_files_name_the_file(tmp_path):
    tex = tmp_path / "a.png"
    Image.new("RGB", (4, 4)).save(tex)
    tile_dir = tmp_path / "tiles" / "0_0"
    mesh = _mesh(str(tex))
    write_tile_mesh(tile_dir, mesh)
    got = read_tile_arrays(tile_dir, ("vertices", "faces", "region"))
    assert sorted(got) == ["faces", "region", "vertices"]
    for name, arr in got.items():
        assert arr.dtype == getattr(mesh, name).dtype and np.array_equal(arr, getattr(mesh, name)), name
    tex.unlink()  # the named arrays need no texture
    assert np.array_equal(read_tile_arrays(tile_dir, ("source",))["source"], mesh.source)
    with pytest.raises(InputError, match="no normals array"):
        read_tile_arrays(tile_dir, ("vertices", "normals"))
    np.savez(tile_dir / "merged.npz", vertices=mesh.vertices, faces=np.array([[0, 1, 7]], np.int32))
    with pytest.raises(InputError, match="merged.npz: face indices out of range"):
        read_tile_arrays(tile_dir, ("vertices", "faces"))
    np.savez(tile_dir / "merged.npz", vertices=mesh.vertices, faces=mesh.faces, region=np.zeros(5, np.int32))
    with pytest.raises(InputError, match="region has 5 values for 2 faces"):
        read_tile_arrays(tile_dir, ("faces", "region"))
    (tile_dir / "merged.npz").write_bytes(b"garbage")
    with pytest.raises(InputError, match="merged.npz"):
        read_tile_arrays(tile_dir, ("vertices",))
    with pytest.raises(InputError, match="run the merge stage"):
        read_tile_arrays(tmp_path / "tiles" / "9_9", ("vertices",))
