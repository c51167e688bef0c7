"""The texture step's cameras: every camera format lands in the campus frame (world minus origin; MLS-frame
cameras.json through the registration), image paths resolve, missing images are reported."""

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.camera_files import write_blocks_exchange, write_colmap
from storage.formats.cameras import Camera, CameraSet, write_cameras_json
from storage.frame import CampusFrame
from tasks.config import CampusConfig
from tasks.repair.texture_inputs import camera_paths, load_cameras

ORIGIN = (589000.0, 2712000.0, 0.0)
CRS = "EPSG:32650"


def world_camera(name: str, x: float) -> Camera:
    """A camera at world (ORIGIN + (x, -10, 2)) looking north (+y), with distortion."""
    r = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # x right, y down (= -z), z forward (= +y)
    c = np.asarray(ORIGIN) + [x, -10.0, 2.0]
    K = np.array([[800.0, 0, 511.5], [0, 800.0, 383.5], [0, 0, 1.0]])
    return Camera(name, K, r, -r @ c, 1024, 768, np.array([-0.08, 0.01, 0.0005, 0.0002, 0.0]))


def images(folder, *names):
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"jpeg")


def config(cameras, images_dir=None) -> CampusConfig:
    return CampusConfig(inputs={"cameras": str(cameras), "images": str(images_dir) if images_dir else None})


FRAME = CampusFrame(origin=ORIGIN, crs=CRS)
WORLD_POINTS = np.asarray(ORIGIN) + np.array([[0.0, 5.0, 3.0], [4.0, 8.0, 1.0], [-3.0, 2.0, 5.5]])


@pytest.mark.parametrize("fmt", ["colmap", "blocks", "json-mesh"])
def test_real_formats_land_in_the_campus_frame(tmp_path, fmt):
    cams = [world_camera("a.jpg", 0.0), world_camera("b.jpg", 3.0)]
    if fmt == "colmap":  # the COLMAP project layout: images/ beside sparse/0
        write_colmap(tmp_path / "sparse" / "0", cams)
        images(tmp_path / "images", "a.jpg", "b.jpg")
        cfg = config(tmp_path / "sparse" / "0")
    elif fmt == "blocks":
        write_blocks_exchange(tmp_path / "AT.xml", cams, crs=CRS)
        images(tmp_path / "photos", "a.jpg", "b.jpg")
        cfg = config(tmp_path / "AT.xml", tmp_path / "photos")
    else:
        write_cameras_json(tmp_path / "cameras.json", CameraSet(cams, "mesh"))
        images(tmp_path, "a.jpg", "b.jpg")
        cfg = config(tmp_path / "cameras.json")
    got = load_cameras(cfg, {}, FRAME)
    assert [c.image.split("/")[-1] for c in got] == ["a.jpg", "b.jpg"]
    local = WORLD_POINTS - np.asarray(ORIGIN)
    for c, ref in zip(got, cams):
        uv, z = c.project(local)
        uv0, z0 = ref.project(WORLD_POINTS)
        np.testing.assert_allclose(uv, uv0, atol=1e-6)
        np.testing.assert_allclose(z, z0, atol=1e-9)
        assert (z > 0).all() and c.dist[0] == -0.08


def test_mls_frame_cameras_follow_the_registration(tmp_path):
    cam = world_camera("a.jpg", 0.0)
    fo = np.asarray(ORIGIN) + [100.0, 0.0, 0.0]  # the file's zero: 100 m east of the campus origin
    local_cam = Camera("a.jpg", cam.K, cam.R, cam.t + cam.R @ fo, cam.width, cam.height, cam.dist)
    write_cameras_json(tmp_path / "cameras.json", CameraSet([local_cam], "MLS", tuple(fo)))
    images(tmp_path, "a.jpg")
    reg = np.eye(4)
    reg[:3, 3] = [0.5, -0.25, 0.1]  # MLS -> mesh: the cameras move with the points
    (got,) = load_cameras(config(tmp_path / "cameras.json"), {"registration": {"matrix": reg.tolist()}}, FRAME)
    local = WORLD_POINTS - np.asarray(ORIGIN)
    np.testing.assert_allclose(got.project(local + reg[:3, 3])[0], cam.project(WORLD_POINTS)[0], atol=1e-6)


def test_missing_images_are_reported(tmp_path):
    cams = [world_camera("a.jpg", 0.0), world_camera("b.jpg", 3.0)]
    write_colmap(tmp_path / "sparse", cams)
    cfg = config(tmp_path / "sparse", tmp_path / "images")
    with pytest.raises(InputError, match="images.txt: none of its 2 images was found"):
        load_cameras(cfg, {}, FRAME)
    images(tmp_path / "images", "b.jpg")
    with pytest.warns(UserWarning, match="1 of 2 camera images not found"):
        got = load_cameras(cfg, {}, FRAME)
    assert [c.image for c in got] == [str(tmp_path / "images" / "b.jpg")]


def test_a_configured_camera_file_must_exist_and_match_the_campus_crs(tmp_path):
    with pytest.raises(InputError, match="camera file not found"):
        load_cameras(config(tmp_path / "AT.xml"), {}, FRAME)
    write_blocks_exchange(tmp_path / "AT.xml", [world_camera("a.jpg", 0.0)], crs="EPSG:2154")
    with pytest.raises(InputError, match="cameras are in EPSG:2154, the campus in EPSG:32650"):
        load_cameras(config(tmp_path / "AT.xml"), {}, FRAME)


def test_camera_paths_default_to_the_synth_layout(tmp_path):
    (tmp_path / "mesh").mkdir()
    images(tmp_path / "images", "cameras.json")
    cfg = CampusConfig(inputs={"mesh": [str(tmp_path / "mesh")]})
    assert camera_paths(cfg) == (tmp_path / "images", tmp_path / "images" / "cameras.json")
    write_colmap(tmp_path / "sparse", [world_camera("a.jpg", 0.0)])
    assert camera_paths(config(tmp_path / "sparse"))[1] == tmp_path / "sparse" / "images.txt"
    assert load_cameras(CampusConfig(), {}, FRAME) == []


def test_an_edited_colmap_intrinsics_file_changes_the_region_fingerprint(tmp_path):
    """COLMAP keeps poses in images.txt and intrinsics + distortion in cameras.txt: editing either re-textures."""
    from tasks.repair.stage import camera_fingerprint

    model = tmp_path / "sparse"
    model.mkdir()
    (model / "images.txt").write_text("# poses\n")
    (model / "cameras.txt").write_text("1 OPENCV 640 480 500 500 320 240 0.01 0 0 0\n")
    cfg = config(model)
    before = camera_fingerprint(cfg)
    (model / "cameras.txt").write_text("1 OPENCV 640 480 500 500 320 240 0.02 0 0 0\n")
    assert camera_fingerprint(cfg) != before
    (model / "images.txt").write_text("# other poses\n")
    assert camera_fingerprint(cfg) not in (before, None)


def test_a_colmap_model_named_by_its_cameras_txt_fingerprints_the_poses_too(tmp_path):
    from tasks.repair.stage import camera_fingerprint

    model = tmp_path / "sparse"
    model.mkdir()
    (model / "images.txt").write_text("# poses\n")
    (model / "cameras.txt").write_text("1 OPENCV 640 480 500 500 320 240 0.01 0 0 0\n")
    cfg = config(model / "cameras.txt")
    before = camera_fingerprint(cfg)
    (model / "images.txt").write_text("# re-solved poses\n")
    assert camera_fingerprint(cfg) != before


def test_cameras_are_read_again_when_the_file_the_images_or_the_registration_change(tmp_path):
    """A worker parses the camera file once for many regions; an edited file, a new image or another
    registration gives the new cameras, not the kept ones."""
    write_cameras_json(tmp_path / "cameras.json", CameraSet([world_camera("a.jpg", 0.0)], "MLS", ORIGIN))
    images(tmp_path, "a.jpg")
    cfg = config(tmp_path / "cameras.json")
    reg = {"registration": {"matrix": np.eye(4).tolist()}}
    (a,) = load_cameras(cfg, reg, FRAME)
    (again,) = load_cameras(cfg, reg, FRAME)
    assert again.image == a.image and np.array_equal(again.centre, a.centre)
    write_cameras_json(tmp_path / "cameras.json", CameraSet([world_camera("a.jpg", 0.0), world_camera("b.jpg", 2.0)],
                                                            "MLS", ORIGIN))
    images(tmp_path, "b.jpg")
    assert [c.image.split("/")[-1] for c in load_cameras(cfg, reg, FRAME)] == ["a.jpg", "b.jpg"]
    moved = np.eye(4)
    moved[:3, 3] = [1.0, 0.0, 0.0]
    a2 = load_cameras(cfg, {"registration": {"matrix": moved.tolist()}}, FRAME)[0]
    np.testing.assert_allclose(a2.centre, a.centre + [1.0, 0.0, 0.0], atol=1e-9)
