"""Registration and the co-registration check against a coarse, LoD2-like mesh.

The scene is built here: five box buildings on both sides of a road along x, on a ground plane. The
mesh is the exact surface with as few triangles as it takes (``trimesh.creation.box``, 12 triangles
per building, the ground in 5 m cells: 492 triangles, vertices metres to tens of metres apart). The
MLS stand-in samples the same true surface where a vehicle on the road sees it: the road-facing
facades, the first 4 m of the side walls and the ground near the road, 8 cm apart with 5 mm noise.
Against the vertex set, registration failed here and the check reported metres for coincident inputs.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from storage.errors import InputError
from synth.generate import similarity
from synth.handmade import jittered_parallelogram as _rect
from tasks.config import RegistrationConfig
from tasks.geometry.distance import point_to_mesh_distance
from tasks.register.align import (
    CoregistrationCheck,
    apply_similarity,
    check_coregistered,
    check_overlap,
    compare_transforms,
    mesh_registration_target,
    register_clouds,
)
from tasks.register.target import faces_in_box, mesh_arrays

# (x0, x1, y0, y1, height), metres; the road is y in (-8, 8)
BUILDINGS = [
    (-38.0, -16.0, 8.0, 22.0, 12.0),
    (-10.0, 9.0, 9.5, 19.5, 17.0),
    (14.0, 36.0, 8.0, 20.0, 8.5),
    (-33.0, -7.0, -21.0, -9.0, 10.0),
    (1.0, 29.0, -22.0, -8.0, 19.0),
]
GROUND = (-45.0, 45.0, -30.0, 30.0)
TRUTH = similarity(1.0003, 0.3, 0.0, 0.0, (0.5, -0.2, 0.1))  # scale, yaw, pitch, roll (deg), t (m)


def _lod2_mesh() -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3) float64, faces (m, 3) int64) of the boxes and a 5 m ground grid."""
    parts = []
    for x0, x1, y0, y1, h in BUILDINGS:
        move = trimesh.transformations.translation_matrix(((x0 + x1) / 2, (y0 + y1) / 2, h / 2))
        parts.append(trimesh.creation.box(extents=(x1 - x0, y1 - y0, h), transform=move))
    xs, ys = np.arange(GROUND[0], GROUND[1] + 1e-9, 5.0), np.arange(GROUND[2], GROUND[3] + 1e-9, 5.0)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    i, j = np.meshgrid(np.arange(len(xs) - 1), np.arange(len(ys) - 1), indexing="ij")
    a = (i * len(ys) + j).ravel()
    b, c = a + len(ys), a + len(ys) + 1
    cells = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, a + 1], 1)])
    ground = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    parts.append(trimesh.Trimesh(ground, cells, process=False))
    mesh = trimesh.util.concatenate(parts)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def _mls(seed: int = 0) -> np.ndarray:
    """(n, 3) float64: what a scanner on the road sees of the true surface, 8 cm apart, 5 mm noise."""
    rng = np.random.default_rng(seed)
    pts = [_rect((-42, -7.5, 0), (84, 0, 0), (0, 15, 0), 0.08, rng)]
    for x0, x1, y0, y1, h in BUILDINGS:
        front, sign = (y0, 1.0) if y0 > 0 else (y1, -1.0)
        pts.append(_rect((x0, front, 0), (x1 - x0, 0, 0), (0, 0, h), 0.08, rng))
        pts += [_rect((x, front, 0), (0, sign * 4.0, 0), (0, 0, h), 0.08, rng) for x in (x0, x1)]
    xyz = np.concatenate(pts)
    return xyz + rng.normal(0, 0.005, xyz.shape)


@pytest.fixture(scope="module")
def scene():
    vertices, faces = _lod2_mesh()
    return vertices, faces, _mls()


def test_the_mesh_is_lod2_like(scene):
    vertices, faces, _ = scene
    edges = np.linalg.norm(vertices[faces] - vertices[faces[:, [1, 2, 0]]], axis=2)
    assert 300 <= len(faces) <= 600 and np.median(edges) >= 5.0  # a few hundred large triangles


def test_registration_recovers_a_similarity_against_the_lod2_mesh(scene):
    vertices, faces, mls = scene
    moved = apply_similarity(np.linalg.inv(TRUTH), mls)
    res = register_clouds(moved, vertices, faces, RegistrationConfig())
    err = compare_transforms(res.matrix, TRUTH, at=moved.mean(axis=0))
    print(f"\nLoD2 registration {res.method}: {err}, {res.seconds:.1f} s, {res.details['seconds']}")
    assert err["rotation_error_deg"] < 0.05
    assert err["translation_error_m"] < 0.02
    assert abs(err["scale_error_pct"]) < 0.05
    assert res.fitness > 0.9 and res.inlier_rmse_m < 0.02  # exact surface: the 5 mm MLS noise dominates


def test_check_on_coincident_inputs_reports_millimetres(scene):
    vertices, faces, mls = scene
    check = check_coregistered(mls, vertices, faces)
    assert isinstance(check, CoregistrationCheck)
    assert check.ok and check.median_m < 0.01 and check.p90_m < 0.02
    assert check.overlap_fraction > 0.99 and check.n_points == check.n_sample > 1000
    res = register_clouds(mls, vertices, faces, RegistrationConfig(enabled=False))  # no warning
    assert np.array_equal(res.matrix, np.eye(4)) and res.details["check"]["median_m"] < 0.01


@pytest.mark.parametrize("offset", [(0.5, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, 0.0, 0.5), (0.3, 0.3, 0.3)])
def test_check_flags_a_half_metre_shift(scene, offset):
    vertices, faces, mls = scene
    check = check_coregistered(mls + offset, vertices, faces)
    assert not check.ok and check.median_m > 0.3, check


def test_check_sees_a_shift_across_walls_whose_normals_lie_on_a_bin_edge():
    """Points all over two boxes on a slab, three times along x: the x-facing walls (normal azimuth 0 or
    180 deg, split by noise between two disjoint 30 deg bins) are ~8 % of the points. A 0.5 m shift
    along x moves only them off the surface; with disjoint bins each half fell below the group share."""
    boxes = [((10, 8, 9), (6, 6, 4.5)), ((8, 10, 6), (22, 20, 3)), ((30, 30, 0.2), (15, 15, -0.1))]
    parts = [
        trimesh.creation.box(size, trimesh.transformations.translation_matrix(np.add(centre, (x0, 0, 0))))
        for x0 in (0.0, 60.0, 120.0)
        for size, centre in boxes
    ]
    mesh = trimesh.util.concatenate(parts)
    pts, _ = trimesh.sample.sample_surface(mesh, 60_000, seed=1)
    pts = pts + np.random.default_rng(0).normal(0, 0.003, pts.shape)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    assert check_coregistered(pts, vertices, faces).ok
    for offset in ((0.5, 0.0, 0.0), (0.0, 0.5, 0.0)):
        check = check_coregistered(pts + offset, vertices, faces)
        assert not check.ok and check.median_m == pytest.approx(0.5, abs=0.05), (offset, check)


def test_a_cloud_10_km_off_raises_naming_both_extents(scene):
    vertices, faces, mls = scene
    both = (
        r"\(campus-local\) \(x 9,9\d\d\.\.10,0\d\d, y -\d+\.\.\d+\) and the mesh \(x -45\.\.45, y -30\.\.30\)"
    )
    with pytest.raises(InputError, match=both):
        check_coregistered(mls + (10_000.0, 0.0, 0.0), vertices, faces)
    with pytest.raises(InputError, match="do not overlap"):
        register_clouds(mls + (10_000.0, 0.0, 0.0), vertices, faces, RegistrationConfig())


def test_check_overlap_names_both_files_in_world_coordinates():
    lo, hi = np.array([589_000.0, 2_712_000.0, 10.0]), np.array([589_400.0, 2_712_300.0, 60.0])
    check_overlap(lo, hi, lo + (399.0, 299.0, 0.0), hi + 1000.0, "mls/strip.laz", "mesh/")  # corners overlap
    with pytest.raises(InputError) as caught:
        check_overlap(lo, hi, lo + (10_000.0, 0, 0), hi + (10_000.0, 0, 0), "mls/strip.laz", "mesh/")
    message = str(caught.value)
    assert "mls/strip.laz (x 589,000..589,400, y 2,712,000..2,712,300)" in message
    assert "mesh/ (x 599,000..599,400, y 2,712,000..2,712,300) do not overlap" in message
    assert "\n" not in message and message.endswith("wrong CRS or UTM zone, units, or mesh offset?")
    with pytest.raises(InputError, match="unknown extent"):
        check_overlap(lo, hi, [np.nan, 0.0], [1.0, 1.0])


def test_registration_target_samples_the_surface_not_the_vertices(scene):
    vertices, faces, _ = scene
    xyz, normals = mesh_registration_target(vertices, faces, spacing_m=0.25, max_samples=10**6, rng=3)
    area = trimesh.Trimesh(vertices, faces, process=False).area
    assert len(xyz) == pytest.approx(area / 0.25**2, rel=0.01)  # one per 0.25 m x 0.25 m
    again, _ = mesh_registration_target(vertices, faces, spacing_m=0.25, max_samples=10**6, rng=3)
    assert np.array_equal(xyz, again)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    dist, face = point_to_mesh_distance(xyz, vertices, faces, return_faces=True)
    assert dist.max() < 1e-9  # every sample lies on the surface ...
    face_normals = trimesh.Trimesh(vertices, faces, process=False).face_normals[face]
    assert np.median(np.abs(np.einsum("ij,ij->i", normals, face_normals))) == pytest.approx(1.0)  # its face's


def test_registration_target_budget():
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [0, 0, 0.001]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 4]])  # two 50 m² faces and a 0.005 m² sliver

    def counts(xyz):
        return np.bincount(point_to_mesh_distance(xyz, v, f, return_faces=True)[1], minlength=3)

    xyz, _ = mesh_registration_target(v, f, spacing_m=1.0, max_samples=1000)
    assert counts(xyz).tolist() == [50, 50, 1]  # within budget: area x density, at least 1 per face
    xyz, _ = mesh_registration_target(v, f, spacing_m=1.0, max_samples=21)
    assert len(xyz) <= 21 and counts(xyz)[2] == 1 and abs(counts(xyz)[0] - counts(xyz)[1]) <= 1
    xyz, _ = mesh_registration_target(v, f, spacing_m=1.0, max_samples=2)
    assert counts(xyz).tolist() == [1, 1, 0]  # fewer samples than faces: area-proportional
    with pytest.raises(ValueError):
        mesh_registration_target(v, f, spacing_m=0.0)


def test_the_target_does_not_depend_on_the_tessellation():
    """A 20 m x 10 m wall as 2 triangles or as 2048: the same number of samples, the same spread."""
    coarse_v = np.array([[0, 0, 0], [20, 0, 0], [20, 0, 10], [0, 0, 10]], float)
    coarse_f = np.array([[0, 1, 2], [0, 2, 3]])
    fine = trimesh.Trimesh(coarse_v, coarse_f, process=False)
    for _ in range(5):
        fine = fine.subdivide()  # 2048 faces of 0.1 m², each smaller than the 0.2 m x 0.2 m cell
    a, _ = mesh_registration_target(coarse_v, coarse_f, spacing_m=0.2)
    b, _ = mesh_registration_target(fine.vertices, fine.faces, spacing_m=0.2)
    assert len(fine.faces) == 2048 and abs(len(a) - len(b)) <= 1
    hist = lambda p: np.histogram2d(p[:, 0], p[:, 2], bins=(4, 2), range=((0, 20), (0, 10)))[0]
    np.testing.assert_allclose(hist(a), hist(b), rtol=0.02)


def test_mesh_inputs_are_checked():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 0, 0]], float)
    with pytest.raises(InputError, match="outside 0..3"):
        mesh_arrays(v, np.array([[0, 1, 4]]))
    with pytest.raises(InputError, match="no faces with finite vertices"):
        mesh_arrays(v, np.array([[0, 1, 3]]))
    with pytest.raises(InputError, match=r"\(m, 3\) integer"):
        mesh_arrays(v, np.array([[0.0, 1.0, 2.0]]))
    _, f = mesh_arrays(v, np.array([[0, 1, 2], [0, 1, 3]]))
    assert f.tolist() == [[0, 1, 2]]
    assert faces_in_box(v, f, (0.5, 0.5), (2.0, 2.0)).tolist() == [0]
    assert faces_in_box(v, f, (1.5, 1.5), (2.0, 2.0)).tolist() == []
