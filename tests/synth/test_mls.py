"""Simulated MLS scan and vehicle trajectories, on scenes of a few boxes built here."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from synth.mls import MlsChunk, MlsParams, simulate_mls
from synth.realism import mls_wall_stats
from synth.scene import FaceClass, Mesh, OccluderClass, Occluders, Scene
from synth.trajectory import TrajectoryParams, build_trajectories, densify, round_corners

NO_ERROR = {"pass_offset_m": (0.0, 0.0), "drift_m_per_s": 0.0, "jitter_m": 0.0}
SOUTH = (0, 1)  # box(): faces 0, 1 face -y; 2, 3 +x; 4, 5 +y; 6, 7 -x; 8, 9 top; 10, 11 bottom


def box(lo, hi, side=FaceClass.WALL, top=FaceClass.ROOF, building=0, color=(200, 180, 160)) -> Mesh:
    """An axis-aligned box, 12 outward-wound triangles (sides ``side``, top and bottom ``top``)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], np.float64)
    quads = [(0, 1, 5, 4), (1, 3, 7, 5), (3, 2, 6, 7), (2, 0, 4, 6), (4, 5, 7, 6), (0, 2, 3, 1)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int64)
    cls = np.array([side] * 8 + [top] * 4, np.uint8)
    return Mesh(v, faces, cls, np.full(12, building, np.int32), np.tile(np.array(color, np.uint8), (12, 1)))


def ground(x0=-60.0, x1=160.0, y0=-80.0, y1=80.0) -> Mesh:
    v = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], np.float64)
    return Mesh(v, np.array([[0, 1, 2], [0, 2, 3]]), np.full(2, FaceClass.GROUND, np.uint8),
                np.full(2, -1, np.int32), np.full((2, 3), 110, np.uint8))


def make_scene(parts: list[Mesh], road_x=(0.0, 60.0), occluders: Mesh | None = None):
    """Scene with ground + parts along one east-west road at y = 0; returns (scene, face offset of each part)."""
    meshes = [ground()] + parts
    offsets = np.cumsum([0] + [m.n_faces for m in meshes])[1:-1]
    road = np.array([[road_x[0], 0.0], [road_x[1], 0.0]])
    occ = Occluders(occluders if occluders is not None else Mesh.empty())
    return Scene(Mesh.concat(meshes), occ, [], [road], (-60.0, -80.0, 160.0, 80.0)), offsets


def scan(scene, params: MlsParams, n_passes=1, traj_kw=None, seed=1):
    trajs = build_trajectories(scene.roads, TrajectoryParams(n_passes=n_passes, **(traj_kw or {})),
                               np.random.default_rng(seed))
    return MlsChunk.concat(list(simulate_mls(scene, trajs, params, np.random.default_rng(seed)))), trajs


def on_faces(cloud: MlsChunk, faces, source=0) -> np.ndarray:
    return (cloud.source == source) & np.isin(cloud.face, faces)


# --- trajectories ----------------------------------------------------------------------------

def test_trajectory_lanes_speed_time_and_offsets():
    tp = TrajectoryParams(n_passes=3, speed_m_s=9.0, pass_offset_m=(0.01, 0.02), drift_m_per_s=0.0, jitter_m=0.0)
    trajs = build_trajectories([np.array([[0.0, 0.0], [90.0, 0.0]])], tp, np.random.default_rng(0))
    assert [t.direction for t in trajs] == [1, -1, 1]
    t0, t1, t2 = trajs
    xyz, heading = t0.pose_at(np.array([t0.t_start, t0.t_start + 5.0]))
    np.testing.assert_allclose(xyz, [[0, -2, 0], [45, -2, 0]], atol=1e-9)  # right lane, 9 m/s
    np.testing.assert_allclose(heading, 0.0, atol=1e-12)
    xyz, heading = t1.pose_at(np.array([t1.t_start]))
    np.testing.assert_allclose(xyz, [[90, 2, 0]], atol=1e-9)  # back along the other lane
    np.testing.assert_allclose(np.abs(heading), np.pi, atol=1e-12)
    assert t0.duration_s == pytest.approx(10.0)
    assert t1.t_start == pytest.approx(t0.t_end + tp.pass_gap_s) and t2.t_start > t1.t_end
    assert 0 < t0.t_start < 604_800 and t2.t_end < 604_800  # seconds of the GPS week
    for t in trajs:  # constant error = the recorded offset, 1-2 cm
        np.testing.assert_allclose(t.error_at(np.array([t.t_start, t.t_end])), [t.offset_m] * 2, atol=1e-15)
        assert 0.01 <= np.linalg.norm(t.offset_m) <= 0.02


def test_trajectory_rounds_corners_and_wanders_by_mm():
    road = np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 50.0]])
    tr = build_trajectories([road], TrajectoryParams(n_passes=1), np.random.default_rng(3))[0]
    t, xyz, heading = tr.sample(0.5)
    assert np.max(np.abs(np.diff(heading))) < np.radians(5.0)  # no jump at the corner
    assert heading[-1] == pytest.approx(np.pi / 2)
    # the lane keeps 2 m right of the road centre line as the vehicle drives it (corner rounded, r = 8 m)
    centre = densify(round_corners(road, 8.0), 0.01)
    d_centre = cKDTree(centre).query(xyz[:, :2])[0]
    np.testing.assert_allclose(d_centre, 2.0, atol=0.01)
    assert np.all(xyz[:, 0] < 52.0 + 1e-9) and np.all(xyz[:, 1] > -2.0 - 1e-9)  # never outside the lane
    wander = tr.error_at(t) - tr.offset_m - (t - tr.t_start)[:, None] * tr.drift_m_per_s
    assert 0.005 < np.sqrt(np.mean(wander**2)) < 0.015


# --- scanner ---------------------------------------------------------------------------------

def test_density_4000_per_m2_at_10m_full_rate():
    scene, off = make_scene([box((-20, 8, 0), (40, 9, 8))], road_x=(0.0, 20.0))
    cloud, _ = scan(scene, MlsParams(), traj_kw=NO_ERROR)
    wall = on_faces(cloud, off[0] + np.array(SOUTH))
    x, z = cloud.xyz[wall, 0], cloud.xyz[wall, 2]
    # cells x 8-12 m, z 1-4 m are seen by both heads at ~10 m horizontal range
    density = np.sum((x >= 8) & (x < 12) & (z >= 1) & (z < 4)) / 12.0
    assert 0.6 * 4000 <= density <= 1.4 * 4000
    assert density == pytest.approx(4000, rel=0.15)  # by construction (see synth.mls docstring)
    assert cloud.n_rays == int(np.floor(20.0 / 9.0 * MlsParams().pulse_rate_hz))


def test_density_falls_with_range_and_scales():
    walls = [box((0, -8, 0), (20, -7, 5)), box((30, -13, 0), (50, -12, 5)), box((60, -23, 0), (80, -22, 5))]
    scene, off = make_scene(walls, road_x=(0.0, 100.0))
    cloud, _ = scan(scene, MlsParams(density_scale=0.1), traj_kw=NO_ERROR)
    dens = []
    for o, (xa, xb) in zip(off, [(7, 13), (37, 43), (67, 73)]):
        sel = on_faces(cloud, o + np.array([4, 5]))  # north faces look at the road
        x, z = cloud.xyz[sel, 0], cloud.xyz[sel, 2]
        dens.append(np.sum((x >= xa) & (x < xb) & (z >= 1.5) & (z < 3.5)) / 12.0)
    d5, d10, d20 = dens
    assert d10 == pytest.approx(400, rel=0.4)  # 4,000 x density_scale
    assert d5 / d10 == pytest.approx(2.0, rel=0.2) and d10 / d20 == pytest.approx(2.0, rel=0.2)  # ~1/range


def test_noise_and_pass_offsets_on_a_flat_wall():
    scene, _ = make_scene([box((-40, 12, 0), (100, 13, 8))], road_x=(0.0, 60.0))
    # errors off, except known constant per-pass offsets: noise is the 5 mm range noise only
    clean = MlsParams.vmx450(head_bias_m=0.0, density_scale=0.1)
    kw = {"pass_offset_m": (0.02, 0.04), "drift_m_per_s": 0.0, "jitter_m": 0.0}
    cloud, trajs = scan(scene, clean, n_passes=2, traj_kw=kw)
    st = mls_wall_stats(cloud, trajs, scene.truth)
    assert st.noise_rms_pass_m == pytest.approx(0.005, abs=0.0015)
    assert st.noise_rms_rotation_m == pytest.approx(0.005, abs=0.0015)
    # pass-to-pass offset along the wall's outward normal (0, -1, 0) recovered to 1.5 mm
    assert st.pass_pairs.tolist() == [[0, 1]]
    expected = -(trajs[1].offset_m[1] - trajs[0].offset_m[1])
    assert st.pass_pair_offset_m[0] == pytest.approx(expected, abs=0.0015)
    assert st.pass_pair_cells[0] > 100
    # default errors (head range bias, trajectory wander): ~5 mm within a rotation, ~1 cm over a pass
    cloud, trajs = scan(scene, MlsParams(density_scale=0.1), n_passes=1)
    st = mls_wall_stats(cloud, trajs, scene.truth)
    assert st.noise_rms_rotation_m == pytest.approx(0.005, abs=0.0015)
    assert 0.007 < st.noise_rms_pass_m < 0.015


def test_nothing_beyond_max_range():
    # the heads look +-35 deg fore and aft: at 82 m they hit x = +-57 m, at 148 m x = +-104 m
    near, far = box((-70, 80, 0), (80, 81, 30)), box((-130, -151, 0), (140, -150, 30))
    scene, off = make_scene([near, far], road_x=(0.0, 10.0))
    params = MlsParams(density_scale=0.05, max_range_m=120.0)
    cloud, _trajs = scan(scene, params, traj_kw=NO_ERROR)
    assert np.all(cloud.range_m <= 120.0)
    assert on_faces(cloud, off[0] + np.array(SOUTH)).sum() > 100  # wall facing the road at 82-100 m
    assert on_faces(cloud, off[1] + np.arange(12)).sum() == 0  # wall at ~148 m: nothing
    horiz = np.hypot(cloud.xyz[:, 0] - np.clip(cloud.xyz[:, 0], 0, 10), cloud.xyz[:, 1] + 2)
    assert horiz.max() < 120.5


def test_parked_car_shadows_the_wall():
    car = box((20, 5.5, 0), (24.5, 7.3, 1.5), OccluderClass.CAR, OccluderClass.CAR, building=7)
    scene, off = make_scene([box((-20, 8, 0), (70, 9, 8))], road_x=(0.0, 45.0), occluders=car)
    cloud, _ = scan(scene, MlsParams(density_scale=0.1), traj_kw=NO_ERROR)
    wall = on_faces(cloud, off[0] + np.array(SOUTH))
    x, z = cloud.xyz[wall, 0], cloud.xyz[wall, 2]

    def count(xa, xb):
        return int(np.sum((x >= xa) & (x < xb) & (z >= 0.05) & (z < 0.9)))

    assert count(21.0, 23.5) == 0  # behind the car for both heads
    assert count(31.0, 33.5) > 300  # same-size patch without a car
    car_pts = cloud.source == 1
    assert car_pts.sum() > 100 and np.all(cloud.face_class[car_pts] == OccluderClass.CAR)


def test_tall_flat_roof_unseen_low_gable_roof_glimpsed():
    tall = box((10, 8, 0), (30, 18, 20))
    house = box((50, 8, 0), (70, 16, 4))
    gable = Mesh(np.array([[50, 8, 4], [70, 8, 4], [70, 12, 6], [50, 12, 6], [70, 16, 4], [50, 16, 4]], np.float64),
                 np.array([[0, 1, 2], [0, 2, 3], [3, 2, 4], [3, 4, 5], [0, 3, 5], [1, 4, 2]]),
                 np.array([FaceClass.ROOF] * 4 + [FaceClass.WALL] * 2, np.uint8),
                 np.full(6, 1, np.int32), np.full((6, 3), 150, np.uint8))
    scene, off = make_scene([tall, house, gable], road_x=(0.0, 90.0))
    cloud, _ = scan(scene, MlsParams(density_scale=0.1), traj_kw=NO_ERROR)
    assert on_faces(cloud, off[0] + np.array(SOUTH)).sum() > 10_000  # its wall is well covered
    assert on_faces(cloud, off[0] + np.array([8, 9])).sum() == 0  # flat roof 20 m up: nothing
    roof = on_faces(cloud, off[2] + np.array([0, 1])).sum()  # gable slope facing the road: grazing
    wall = on_faces(cloud, off[1] + np.array(SOUTH)).sum()
    assert roof > 20 and roof / (20 * np.hypot(4, 2)) < 0.5 * wall / (20 * 4)  # per m^2
    assert on_faces(cloud, off[2] + np.array([2, 3])).sum() == 0  # the far slope


def test_deterministic_time_ordered_and_consistent():
    car = box((8, 3, 0), (12.5, 4.8, 1.5), OccluderClass.CAR, OccluderClass.CAR, building=1, color=(20, 40, 200))
    scene, _off = make_scene([box((-5, 8, 0), (30, 9, 6), color=(201, 180, 160))], road_x=(0.0, 20.0), occluders=car)
    params = MlsParams(density_scale=0.02, max_rays_per_chunk=20_000)
    trajs = build_trajectories(scene.roads, TrajectoryParams(n_passes=2), np.random.default_rng(5))
    runs = [list(simulate_mls(scene, trajs, params, np.random.default_rng(9))) for _ in range(2)]
    a, b = (MlsChunk.concat(r) for r in runs)
    assert len(runs[0]) > 4 and all(c.n_rays <= 20_000 for c in runs[0])
    for name in ("xyz", "gps_time", "intensity", "rgb", "face", "source", "scanner_id", "profile_id"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    other = MlsChunk.concat(list(simulate_mls(scene, trajs, params, np.random.default_rng(10))))
    assert len(other) != len(a) or not np.array_equal(other.xyz, a.xyz)
    assert np.all(np.diff(a.gps_time) >= 0)  # time order within and across chunks and passes
    assert np.array_equal(np.unique(a.pass_id), [0, 1]) and np.all(np.diff(a.pass_id.astype(int)) >= 0)
    # attributes follow the face that was hit
    t, o = a.source == 0, a.source == 1
    np.testing.assert_array_equal(a.face_class[t], scene.truth.face_class[a.face[t]])
    np.testing.assert_array_equal(a.rgb[t], scene.truth.face_color[a.face[t]].astype(np.uint16) * 257)
    np.testing.assert_array_equal(a.rgb[o], np.tile([20 * 257, 40 * 257, 200 * 257], (o.sum(), 1)))
    assert o.sum() > 0 and np.all(a.face_class[o] == OccluderClass.CAR)
    assert a.intensity.max() > 1000 and a.xyz.dtype == np.float64 and a.face.dtype == np.int64
