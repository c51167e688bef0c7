"""The shipped EGM96 geoid and user PROJ grids (storage.geoid)."""

from __future__ import annotations

import numpy as np
import pytest

from storage.errors import InputError
from storage.geoid import egm96_undulation, geoid_of, grid_geoid, write_gtx

# NGA's EGM96 test points (lat, lon, N metres; their spline interpolation of the 15' grid)
NGA_POINTS = [(38.6281550, 269.7791550, -31.628), (-14.6212170, 305.0211140, -2.969),
              (46.8743190, 102.4487290, -43.575), (-23.6174460, 133.8747120, 15.871),
              (38.6254730, 359.9995000, 50.066), (-0.4667440, 0.0023000, 17.329)]


def test_egm96_matches_ngas_test_points():
    lat, lon, ref = (np.array(c) for c in zip(*NGA_POINTS))
    got = egm96_undulation(lat, lon)
    assert np.abs(got - ref).max() < 0.07  # bilinear against NGA's spline
    assert egm96_undulation(lat[0], lon[0] - 360.0) == pytest.approx(got[0])  # longitudes wrap
    assert np.isfinite(egm96_undulation(np.array([90.0, -90.0]), np.array([0.0, 180.0]))).all()  # poles


def test_a_user_grid_is_read_by_proj(tmp_path):
    lat, lon = np.arange(50.0, 54.01, 0.25), np.arange(3.0, 7.01, 0.25)
    n = 40.0 + (lat[:, None] - 50.0) + 0.5 * (lon[None, :] - 3.0)
    g = geoid_of(str(write_gtx(tmp_path / "g.gtx", 50.0, 3.0, 0.25, 0.25, n)))
    q_lat, q_lon = np.array([52.37, 51.1, 50.0]), np.array([4.89, 3.3, 3.0])
    assert g.undulation(q_lat, q_lon) == pytest.approx(40.0 + (q_lat - 50.0) + 0.5 * (q_lon - 3.0), abs=1e-4)
    with pytest.raises(InputError, match="does not cover"):
        g.undulation(np.array([10.0]), np.array([10.0]))
    with pytest.raises(InputError, match="not found"):
        grid_geoid(tmp_path / "missing.gtx")
    (tmp_path / "junk.gtx").write_bytes(b"not a grid")
    with pytest.raises(InputError, match="junk.gtx"):
        grid_geoid(tmp_path / "junk.gtx").undulation(np.array([52.0]), np.array([4.0]))
    assert geoid_of(None).spec == geoid_of("EGM96").spec == "egm96"
