"""Vehicle cameras: poses, the OpenCV projection convention, and ray-cast rendering."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

from synth.cameras import (
    LEFT,
    RIGHT,
    CameraParams,
    Exposure,
    place_cameras,
    project,
    render,
    render_cameras,
    transform_pose,
    write_images,
)
from synth.raycast import SceneCaster
from synth.scene import FaceClass, Mesh, OccluderClass, Occluders, Scene
from synth.trajectory import TrajectoryParams, build_trajectories

WALL_RGB = (200, 180, 160)
CAR_RGB = (20, 40, 200)
NO_ERROR = TrajectoryParams(n_passes=1, pass_offset_m=(0.0, 0.0), drift_m_per_s=0.0, jitter_m=0.0)
PARAMS = CameraParams(width=160, height=120, every_m=10.0, mounts=(LEFT, RIGHT))


def box(lo, hi, cls, building, color) -> Mesh:
    """Axis-aligned box; faces 0, 1 face -y (face 0 is the lower-right half), 2, 3 +x, 4, 5 +y, 6, 7 -x, 8-11 top/bottom."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], np.float64)
    quads = [(0, 1, 5, 4), (1, 3, 7, 5), (3, 2, 6, 7), (2, 0, 4, 6), (4, 5, 7, 6), (0, 2, 3, 1)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int64)
    return Mesh(v, faces, np.full(12, cls, np.uint8), np.full(12, building, np.int32),
                np.tile(np.array(color, np.uint8), (12, 1)))


@pytest.fixture(scope="module")
def scene() -> Scene:
    g = Mesh(np.array([[-60, -80, 0], [160, -80, 0], [160, 80, 0], [-60, 80, 0]], np.float64),
             np.array([[0, 1, 2], [0, 2, 3]]), np.full(2, FaceClass.GROUND, np.uint8),
             np.full(2, -1, np.int32), np.full((2, 3), 110, np.uint8))
    wall = box((-20, 8, 0), (60, 9, 8), FaceClass.WALL, 0, WALL_RGB)  # truth faces 2.. 13
    car = box((20, 5.5, 0), (24.5, 7.3, 1.5), OccluderClass.CAR, 1, CAR_RGB)
    return Scene(Mesh.concat([g, wall]), Occluders(car), [], [np.array([[0.0, 0.0], [40.0, 0.0]])],
                 (-60.0, -80.0, 160.0, 80.0))


@pytest.fixture(scope="module")
def cams(scene) -> list[Exposure]:
    return place_cameras(build_trajectories(scene.roads, NO_ERROR), PARAMS)


def cam_at(cams, x, mount):
    return next(c for c in cams if c.mount == mount and abs(c.centre[0] - x) < 1e-9)


def test_poses_follow_the_opencv_convention(cams):
    assert len(cams) == 4 * 2 and len({c.image for c in cams}) == 8  # s = 0, 10, 20, 30 m; two mounts
    assert np.all(np.diff([c.timestamp for c in cams[::2]]) == pytest.approx(10.0 / 9.0))
    c = cam_at(cams, 0.0, "left")
    np.testing.assert_allclose(c.centre, [0.0, -2.0, 2.3], atol=1e-12)
    np.testing.assert_allclose(c.R @ c.R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(c.R) == pytest.approx(1.0)
    pitch = np.radians(10.0)
    np.testing.assert_allclose(c.R[2], [0.0, np.cos(pitch), np.sin(pitch)], atol=1e-12)  # looks north, 10 deg up
    ahead = c.centre + 10.0 * c.R[2]
    pts = np.array([ahead, ahead + [1.0, 0, 0], ahead + [0, 0, 1.0], c.centre - c.R[2]])
    uv, depth = project(pts, c)
    np.testing.assert_allclose(uv[0], [79.5, 59.5], atol=1e-9)  # principal point ((W-1)/2, (H-1)/2)
    assert depth[0] == pytest.approx(10.0)
    assert uv[1, 0] > 79.5  # +x (east) is to the right for a north-looking camera
    assert uv[2, 1] < 59.5  # up is towards row 0 (y down)
    assert depth[3] < 0  # behind
    j = c.to_json()
    assert set(j) == {"image", "K", "R", "t", "width", "height", "timestamp"}
    assert np.array(j["K"]).shape == (3, 3) and j["K"][0][0] == pytest.approx(80.0)  # 90 deg hfov, 160 px
    json.dumps(j)


def test_projected_truth_point_lands_on_its_face(scene, cams):
    caster = SceneCaster(scene.truth, scene.occluders.mesh)
    c = cam_at(cams, 10.0, "left")
    r = render(caster, c, PARAMS)
    point = np.array([[12.0, 8.0, 1.0]])  # on wall face 0 (truth face 2), lower-right half of the facade quad
    (u, v), depth = project(point, c)[0][0], project(point, c)[1][0]
    row, col = round(v), round(u)
    assert 0 <= row < 120 and 0 <= col < 160
    assert r.source[row, col] == 0 and r.face[row, col] == 2
    assert r.depth[row, col] == pytest.approx(depth, abs=0.05)
    # flat wall facing away from the sun: ambient only
    assert tuple(r.rgb[row, col]) == tuple(np.round(np.array(WALL_RGB) * PARAMS.ambient).astype(np.uint8))


def test_parked_car_hides_the_wall_behind_it(scene, cams):
    caster = SceneCaster(scene.truth, scene.occluders.mesh)
    c = cam_at(cams, 20.0, "left")
    r = render(caster, c, PARAMS)
    for point, source, face in [((22.0, 5.5, 1.0), 1, 1), ((22.0, 8.0, 0.5), 1, None), ((22.0, 8.0, 5.0), 0, 3)]:
        (u, v) = project(np.array([point]), c)[0][0]
        row, col = round(v), round(u)
        assert r.source[row, col] == source
        if face is not None:
            assert r.face[row, col] == face
    car = r.source == 1
    assert car.sum() > 50 and np.all(r.rgb[car][:, 2] > r.rgb[car][:, 0])  # blue car


def test_sky_and_ground(scene, cams):
    c = cam_at(cams, 10.0, "right")  # looks south over open ground
    r = render(SceneCaster(scene.truth, scene.occluders.mesh), c, PARAMS)
    assert np.all(r.source[0] == -1) and np.all(r.rgb[0] == PARAMS.sky_rgb) and np.all(np.isinf(r.depth[0]))
    assert np.all(r.source[-1] == 0) and set(np.unique(r.face[-1])) <= {0, 1}


def test_recorded_pose_carries_the_trajectory_error(scene, tmp_path):
    trajs = build_trajectories(scene.roads, TrajectoryParams(n_passes=1), np.random.default_rng(4))
    small = CameraParams(width=48, height=36, every_m=20.0, mounts=(LEFT,))
    with_err = place_cameras(trajs, small)
    without = place_cameras(trajs, replace(small, apply_trajectory_error=False))
    caster = SceneCaster(scene.truth, scene.occluders.mesh)
    for a, b in zip(with_err, without):
        np.testing.assert_allclose(a.R, b.R)
        np.testing.assert_allclose(a.centre - b.centre, a.error_m, atol=1e-12)
        assert 0.001 < np.linalg.norm(a.error_m) < 0.1
        np.testing.assert_array_equal(render(caster, a, small).rgb, render(caster, b, small).rgb)
    # poses moved by a similarity project moved points to the same pixels
    ang, s = np.radians(2.0), 1.003
    m = np.eye(4)
    m[:3, :3] = s * np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    m[:3, 3] = [1.5, -2.0, 0.3]
    cam = with_err[0]
    pts = np.array([[12.0, 8.0, 1.0], [3.0, 8.0, 6.0]])
    r_new, t_new = transform_pose(cam, m)
    moved = Exposure(cam.image, cam.K, r_new, t_new, cam.width, cam.height, cam.timestamp, 0, "left", cam.error_m)
    np.testing.assert_allclose(project(pts @ m[:3, :3].T + m[:3, 3], moved)[0], project(pts, cam)[0], atol=1e-9)
    # writing: files and cameras.json entries
    images, cams = render_cameras(scene, trajs, every_m=20.0, size=(48, 36), rng=np.random.default_rng(0),
                                  params=CameraParams(mounts=(LEFT, RIGHT)))
    entries = write_images(tmp_path, images, cams, m, None, prefix="00_")
    assert len(entries) == len(cams) == 4
    assert entries[0]["image"] == "00_" + cams[0].image and (tmp_path / entries[0]["image"]).exists()
    assert Image.open(tmp_path / entries[0]["image"]).size == (48, 36)
    np.testing.assert_allclose(entries[0]["R"], transform_pose(cams[0], m)[0])
