"""E57 point clouds (storage.formats.e57): scans with poses, colours and invalid points, written with pye57 and
read back through the points registry; broken files give one line naming the file."""

from __future__ import annotations

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.points import read_header, read_points


def _quat_z(deg: float) -> np.ndarray:
    a = np.radians(deg) / 2
    return np.array([np.cos(a), 0.0, 0.0, np.sin(a)])  # w, x, y, z


def _write(path, scans):
    """scans: [(xyz (n, 3), rgb (n, 3) uint8, invalid (n,) bool, quaternion, translation)]."""
    import pye57

    with pye57.E57(str(path), mode="w") as e:
        for xyz, rgb, invalid, q, t in scans:
            data = {"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2],
                    "colorRed": rgb[:, 0], "colorGreen": rgb[:, 1], "colorBlue": rgb[:, 2],
                    "intensity": np.linspace(0, 1, len(xyz)), "cartesianInvalidState": invalid.astype(np.int8)}
            e.write_scan_raw(data, rotation=q, translation=t)
    return path


def test_scans_are_posed_filtered_and_coloured(tmp_path):
    rng = np.random.default_rng(3)
    a = rng.uniform(-5, 5, (500, 3))
    b = rng.uniform(-5, 5, (300, 3))
    rgb_a = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    rgb_b = rng.integers(0, 256, (300, 3)).astype(np.uint8)
    inv_b = np.zeros(300, bool)
    inv_b[::10] = True
    t_a, t_b = np.array([589_000.0, 2_712_000.0, 15.0]), np.array([589_020.0, 2_712_010.0, 16.0])
    path = _write(tmp_path / "scan.e57", [(a, rgb_a, np.zeros(500, bool), _quat_z(0), t_a),
                                          (b, rgb_b, inv_b, _quat_z(90), t_b)])
    pts = read_points(path)
    rot90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    expect = np.concatenate([a + t_a, b[~inv_b] @ rot90.T + t_b])
    assert len(pts) == 500 + 270  # the invalid points of scan b dropped
    np.testing.assert_allclose(pts.xyz, expect, atol=1e-6)
    np.testing.assert_array_equal(pts.rgb, np.concatenate([rgb_a, rgb_b[~inv_b]]).astype(np.uint16) * 257)
    assert pts.extra["intensity"].dtype == np.float32
    info = read_header(path)
    assert info.point_count == 770 and info.has_rgb
    np.testing.assert_allclose(info.bounds, [expect.min(axis=0), expect.max(axis=0)], atol=1e-6)


def test_broken_e57_is_one_line(tmp_path):
    good = _write(tmp_path / "good.e57", [(np.zeros((10, 3)) + 1, np.zeros((10, 3), np.uint8),
                                           np.zeros(10, bool), _quat_z(0), np.zeros(3))])
    bad = tmp_path / "bad.e57"
    bad.write_bytes(b"ASTM-E57" + b"\0" * 100)
    cut = tmp_path / "cut.e57"
    cut.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    for p in (bad, cut):
        with pytest.raises(InputError) as e:
            read_points(p)
        assert str(p) in str(e.value) and "\n" not in str(e.value)
