"""Camera files: one camera with lens distortion, written in every supported format and read back, projects
world points to the same pixels; distortion is applied (checked against a hand computation); broken files
give one InputError naming the file."""

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.camera_files import (
    camera_format,
    quat_to_rot,
    read_blocks_exchange,
    read_cameras,
    read_colmap,
    rot_to_quat,
    write_blocks_exchange,
    write_colmap,
    write_colmap_bin,
)
from storage.formats.cameras import Camera, CameraSet, write_cameras_json

WORLD_CENTRE = np.array([589123.40, 2712345.60, 32.10])  # a UTM-sized position: float64 throughout


def rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """World-to-camera rotation looking at azimuth yaw, pitched up, rolled about the optical axis."""
    z = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    r = np.stack([x, np.cross(z, x), z])
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]]) @ r


def distorted_camera(k3: float = 0.004) -> Camera:
    K = np.array([[1510.0, 0.0, 1031.3], [0.0, 1512.5, 760.8], [0.0, 0.0, 1.0]])
    r = rotation(0.7, 0.15, 0.05)
    return Camera("DJI_0042.JPG", K, r, -r @ WORLD_CENTRE, 2048, 1536,
                  np.array([-0.112, 0.041, 0.0007, -0.0004, k3]))


def points_in_view(cam: Camera, n: int = 200) -> np.ndarray:
    """(n, 3) world points 5-40 m in front of ``cam``, spread over the whole image (corners included)."""
    rng = np.random.default_rng(3)
    xy = rng.uniform([-0.68, -0.5], [0.68, 0.5], (n, 2))
    xy[:4] = [[-0.68, -0.5], [0.68, -0.5], [-0.68, 0.5], [0.68, 0.5]]
    depth = rng.uniform(5.0, 40.0, n)
    xc = np.c_[xy * depth[:, None], depth]
    return (xc - cam.t) @ cam.R  # R^T (x_c - t)


def test_quaternion_round_trip():
    for ang in [(0.1, 0.2, 0.3), (3.0, -1.2, 2.9), (-2.5, 1.5, -3.1)]:
        r = rotation(*ang)
        np.testing.assert_allclose(quat_to_rot(rot_to_quat(r)), r, atol=1e-12)
    np.testing.assert_allclose(rot_to_quat(np.diag([1.0, -1.0, -1.0])), [0, 1, 0, 0], atol=1e-12)


@pytest.mark.parametrize("k3", [0.0, 0.004])  # OPENCV / FULL_OPENCV in COLMAP
def test_every_format_projects_a_world_point_to_the_same_pixel(tmp_path, k3):
    cam = distorted_camera(k3)
    pts = points_in_view(cam)
    uv0, z0 = cam.project(pts)
    inside = (uv0 >= 0).all(1) & (uv0[:, 0] <= cam.width - 1) & (uv0[:, 1] <= cam.height - 1)
    assert inside.sum() > 150 and (z0 > 0).all()

    write_cameras_json(tmp_path / "cameras.json", CameraSet([cam], "mesh"))
    write_colmap(tmp_path / "sparse" / "0", [cam])
    write_colmap_bin(tmp_path / "bin" / "0", [cam])
    write_blocks_exchange(tmp_path / "block.xml", [cam], crs="EPSG:32650")
    write_blocks_exchange(tmp_path / "block_mm.xml", [cam], focal_mm=True)
    read = {
        "json": read_cameras(tmp_path / "cameras.json"),
        "colmap folder": read_cameras(tmp_path / "sparse" / "0"),
        "colmap images.txt": read_cameras(tmp_path / "sparse" / "0" / "images.txt"),
        "colmap binary folder": read_cameras(tmp_path / "bin" / "0"),
        "colmap images.bin": read_cameras(tmp_path / "bin" / "0" / "images.bin"),
        "blocks": read_cameras(tmp_path / "block.xml"),
        "blocks mm": read_cameras(tmp_path / "block_mm.xml"),
    }
    assert read["blocks"].crs == "EPSG:32650" and read["colmap folder"].fmt == "colmap"
    model = (tmp_path / "sparse" / "0" / "cameras.txt").read_text().splitlines()[1].split()[1]
    assert model == ("OPENCV" if k3 == 0 else "FULL_OPENCV")
    for name, cs in read.items():
        (c,) = cs.cameras
        assert c.image == "DJI_0042.JPG" and (c.width, c.height) == (2048, 1536), name
        uv, z = c.project(pts)
        err = np.abs(uv - uv0).max()
        assert err < 0.5, f"{name}: {err:.3g} px"
        assert err < 1e-6, f"{name}: {err:.3g} px"  # every format is lossless for this model
        np.testing.assert_allclose(z, z0, rtol=1e-9)


def test_distortion_moves_a_corner_point_by_the_hand_computed_amount():
    K = np.array([[1000.0, 0.0, 1023.5], [0.0, 1000.0, 767.5], [0.0, 0.0, 1.0]])
    cam = Camera("a.jpg", K, np.eye(3), np.zeros(3), 2048, 1536, np.array([-0.1, 0.02, 0.001, -0.002, 0.0]))
    pinhole = Camera("a.jpg", K, np.eye(3), np.zeros(3), 2048, 1536)
    p = np.array([[3.0, -2.0, 5.0]])  # normalised (0.6, -0.4): near the top-right corner
    # by hand: r2 = 0.52; g = 1 - 0.1 * 0.52 + 0.02 * 0.52**2 = 0.953408
    # x_d = 0.6 g + 2 p1 x y + p2 (r2 + 2 x^2) = 0.5720448 - 0.00048 - 0.00248 = 0.5690848
    # y_d = -0.4 g + p1 (r2 + 2 y^2) + 2 p2 x y = -0.3813632 + 0.00084 + 0.00096 = -0.3795632
    uv, z = cam.project(p)
    np.testing.assert_allclose(uv, [[1023.5 + 569.0848, 767.5 - 379.5632]], atol=1e-9)
    uv_pin, _ = pinhole.project(p)
    np.testing.assert_allclose(uv_pin, [[1623.5, 367.5]])
    np.testing.assert_allclose(uv - uv_pin, [[-30.9152, 20.4368]], atol=1e-9)
    assert z[0] == 5.0


def test_points_beyond_the_fold_of_the_radial_model_do_not_project():
    cam = Camera("a.jpg", np.diag([1000.0, 1000.0, 1.0]), np.eye(3), np.zeros(3), 100, 100,
                 np.array([-0.3, 0.0, 0.0, 0.0, 0.0]))
    # 1 + 3 k1 r^2 > 0 only while r^2 < 1.11: a point at 80 deg off-axis would fold back into the image
    uv, _ = cam.project(np.array([[0.1, 0.0, 1.0], [5.7, 0.0, 1.0]]))
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()


def test_format_is_chosen_by_name(tmp_path):
    assert camera_format(tmp_path) == "colmap"
    assert camera_format(tmp_path / "x" / "images.txt") == "colmap"
    assert camera_format(tmp_path / "x" / "cameras.bin") == "colmap"
    assert camera_format(tmp_path / "AT.xml") == "blocksexchange"
    assert camera_format(tmp_path / "cameras.json") == "cameras.json"
    with pytest.raises(InputError, match="unknown camera file"):
        camera_format(tmp_path / "poses.csv")


def _colmap(tmp_path):
    write_colmap(tmp_path, [distorted_camera(), distorted_camera(0.0)])
    return tmp_path / "cameras.txt", tmp_path / "images.txt"


def _edit(p, fn):
    p.write_text(fn(p.read_text()))


@pytest.mark.parametrize("breaks, says", [
    (lambda c, i: _edit(i, lambda s: s[: s.index(" DJI")]), "images.txt: line 2: expected IMAGE_ID"),
    (lambda c, i: _edit(i, lambda s: s.replace("0.", "O.", 1)), "images.txt: line 2: not a number"),
    (lambda c, i: _edit(c, lambda s: s.replace("FULL_OPENCV", "FISHEYE", 1)), "cameras.txt: line 2: camera model "
     "FISHEYE is not supported"),
    (lambda c, i: _edit(c, lambda s: s.replace(" 2048 1536", " 2048 1536 7", 1)), "FULL_OPENCV takes 12"),
    (lambda c, i: _edit(i, lambda s: s.replace(" 1 DJI", " 9 DJI")), "camera 9 is not in cameras.txt"),
    (lambda c, i: c.unlink(), "cameras.txt: COLMAP text model incomplete"),
    (lambda c, i: (i.unlink(), i.with_suffix(".bin").write_bytes(b"\0")), "COLMAP text model incomplete: images.txt"),
    (lambda c, i: i.write_text("# nothing\n"), "no images"),
])
def test_broken_colmap_models_name_the_file_and_line(tmp_path, breaks, says):
    c, i = _colmap(tmp_path)
    breaks(c, i)
    with pytest.raises(InputError, match=says.replace("(", r"\(")):
        read_colmap(tmp_path)


def _colmap_bin(tmp_path):
    write_colmap_bin(tmp_path, [distorted_camera(), distorted_camera(0.0)])
    return tmp_path / "cameras.bin", tmp_path / "images.bin"


def _cut(p, n):
    p.write_bytes(p.read_bytes()[:n])


def _patch(p, offset, raw):
    b = bytearray(p.read_bytes())
    b[offset:offset + len(raw)] = raw
    p.write_bytes(bytes(b))


@pytest.mark.parametrize("breaks, says", [
    (lambda c, i: _cut(i, 100), "images.bin: image 1: truncated"),
    (lambda c, i: _cut(i, 60), "images.bin: truncated at byte 8"),
    (lambda c, i: _cut(c, 30), "cameras.bin: truncated"),
    (lambda c, i: _patch(c, 12, (99).to_bytes(4, "little")), "cameras.bin: camera 1: unknown model id 99"),
    (lambda c, i: _patch(c, 12, (5).to_bytes(4, "little")), "OPENCV_FISHEYE is not supported"),
    (lambda c, i: _patch(i, 8 + 4 + 56, (7).to_bytes(4, "little")), "image 1: camera 7 is not in cameras.bin"),
    (lambda c, i: c.unlink(), "cameras.bin: COLMAP binary model incomplete"),
    (lambda c, i: i.write_bytes((0).to_bytes(8, "little")), "no images"),
])
def test_broken_colmap_binary_models_name_the_file(tmp_path, breaks, says):
    c, i = _colmap_bin(tmp_path)
    assert len(read_colmap(tmp_path).cameras) == 2
    breaks(c, i)
    with pytest.raises(InputError, match=says) as e:
        read_colmap(tmp_path)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("breaks, says", [
    (lambda s: s[: len(s) // 2], "not a readable BlocksExchange XML"),
    (lambda s: s.replace("<M_11>", "<M_11>x"), "<M_11> is not a number"),
    (lambda s: s.replace("FocalLengthPixels", "Focal"), "has no <FocalLength>"),
    (lambda s: s.replace("<M_00>", "<M_00>2"), "R is not a rotation"),
    (lambda s: s.replace("BlocksExchange", "Blocks"), "root element <Blocks>"),
    (lambda s: s.replace("XRightYDown", "XDownYLeft"), "CameraOrientation"),
])
def test_broken_blocks_exchange_names_the_file(tmp_path, breaks, says):
    p = tmp_path / "block.xml"
    write_blocks_exchange(p, [distorted_camera()])
    _edit(p, breaks)
    with pytest.raises(InputError) as e:
        read_blocks_exchange(p)
    assert says in str(e.value) and str(e.value).startswith(str(p))


def test_blocks_exchange_skips_unposed_photos_and_counts_them(tmp_path):
    p = tmp_path / "block.xml"
    write_blocks_exchange(p, [distorted_camera(), distorted_camera()])
    s = p.read_text()
    a = s.index("<Pose>")
    p.write_text(s[:a] + s[s.index("</Pose>") + len("</Pose>"):])
    cs = read_blocks_exchange(p)
    assert len(cs.cameras) == 1 and cs.skipped == 1


def test_broken_cameras_json(tmp_path):
    p = tmp_path / "cameras.json"
    write_cameras_json(p, CameraSet([distorted_camera()], "MLS", (1.0, 2.0, 3.0)))
    cs = read_cameras(p)
    assert cs.frame == "MLS" and cs.frame_origin == (1.0, 2.0, 3.0)
    p.write_text(p.read_text()[:200])
    with pytest.raises(InputError, match="not a cameras.json"):
        read_cameras(p)
    with pytest.raises(InputError, match="camera file not found"):
        read_cameras(tmp_path / "missing.json")
