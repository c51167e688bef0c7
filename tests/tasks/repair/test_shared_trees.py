"""The repair's queries take the caller's k-d tree: the same answers as a tree built inside, and the tree
passed is the one they search (a tree of other points changes the answer)."""

import numpy as np
from scipy.spatial import cKDTree

from tasks.repair.fuse import FusionParams, graph_cut_fuse
from tasks.repair.keep import covered_along_normal, unseen_faces
from tasks.repair.region_geometry import in_view
from tasks.repair.support import unsupported_share


def _wall(rng, n=2000, x0=0.0):
    """Noisy points of a 2 x 2 m wall at y = 0 (normals +y), from x0."""
    p = np.c_[x0 + 2 * rng.random(n), 0.01 * rng.standard_normal(n), 2 * rng.random(n)]
    return p, np.tile([0.0, 1.0, 0.0], (n, 1))


def _mesh(x0=0.0, y=0.0, step=0.25):
    """A 2 x 2 m square grid mesh at y, from x0: ((v, 3) vertices, (f, 3) faces)."""
    g = np.arange(0, 2.0 + 1e-9, step)
    xs, zs = np.meshgrid(g, g, indexing="ij")
    v = np.c_[x0 + xs.ravel(), np.full(xs.size, y), zs.ravel()]
    n = len(g)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).ravel()
    f = np.r_[np.c_[a, a + n, a + 1], np.c_[a + 1, a + n, a + n + 1]]
    return v, f


def test_each_query_gives_the_same_answer_with_the_callers_tree_and_searches_that_tree():
    rng = np.random.default_rng(3)
    pts, pn = _wall(rng)
    other = _wall(rng, x0=5.0)[0]  # the same wall 5 m away: a tree of it must change every answer below
    v, f = _mesh(y=0.05)
    vn = np.tile([0.0, 1.0, 0.0], (len(v), 1))
    half = v[:, 0] < 1.0  # half the mesh over the scanned wall, half beside it
    v[~half, 0] += 4.0
    calls = {
        "in_view": lambda t: in_view(v, vn, pts, radius_m=0.2, cone_deg=30, tree=t),
        "covered": lambda t: covered_along_normal(v, vn, pts, pn, depth_m=0.2, lateral_m=0.08, tree=t),
        "unseen": lambda t: unseen_faces(v, f, pts, np.zeros(len(v), bool), clear_m=0.2, step_m=0.1, tree=t),
        "unsupported": lambda t: unsupported_share(v, f, pts, pn, np.zeros((0, 3)), np.zeros((0, 3), np.int64),
                                                   reach_m=0.3, tree=t),
    }
    for name, call in calls.items():
        own = call(None)
        assert np.array_equal(call(cKDTree(pts)), own), name
        assert not np.array_equal(call(cKDTree(other)), own), name


def test_the_graph_cut_with_the_callers_tree_equals_the_one_it_builds():
    rng = np.random.default_rng(4)
    pts, pn = _wall(rng, n=1500)
    v, _ = _mesh(y=0.1)
    v[v[:, 0] > 1.0, 1] = 0.0  # half the mesh 10 cm in front of the scan, half on it: the cut decides per vertex
    vn = np.tile([0.0, 1.0, 0.0], (len(v), 1))
    p = FusionParams()
    own = graph_cut_fuse(v, vn, pts, pn, p)
    shared = graph_cut_fuse(v, vn, pts, pn, p, mls_tree=cKDTree(pts))
    assert np.array_equal(own.replaced, shared.replaced) and np.array_equal(own.accepted, shared.accepted)
    assert own.energy == shared.energy
    assert own.replaced.any() and not own.replaced.all()
