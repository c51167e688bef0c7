"""Neighbourhood cues (ms3d_model.context): max / mean / count over the 26 neighbouring cells."""

import numpy as np

from ms3d_model.context import CONTEXT_COLUMNS, context_cues, with_context
from ms3d_model.cues import CONTEXT_CUE_NAMES, CUE_NAMES, N_PAIR_CUES, OWN_CUE_NAMES, PAIR_CUE_NAMES


def _cues(values: dict[str, list[float]], n: int) -> np.ndarray:
    c = np.zeros((n, N_PAIR_CUES), np.float32)
    for name, v in values.items():
        c[:, PAIR_CUE_NAMES.index(name)] = v
    return c


def test_block_of_cells_sees_its_neighbours_and_nothing_beyond():
    ijk = np.array([[i, j, 0] for i in range(3) for j in range(3)] + [[10, 10, 0]])  # a 3 x 3 block and a loner
    v = np.arange(10, dtype=float)
    v[9] = 100.0  # the loner's large value must reach nobody
    ctx = dict(zip(CONTEXT_CUE_NAMES, context_cues(_cues({"p2m_p90": v}, 10), ijk).T))
    centre = 4  # cell (1, 1): all 8 others of the block are its neighbours
    assert ctx["nb_count"][centre] == 8
    assert ctx["nb_max_p2m_p90"][centre] == 8.0
    assert np.isclose(ctx["nb_mean_p2m_p90"][centre], (36 - 4) / 8)
    assert ctx["nb_count"][0] == 3 and ctx["nb_max_p2m_p90"][0] == 4.0  # corner (0, 0): (0,1), (1,0), (1,1)
    assert ctx["nb_count"][9] == 0 and ctx["nb_max_p2m_p90"][9] == 0.0 and ctx["nb_mean_p2m_p90"][9] == 0.0
    assert ctx["nb_max_p2m_p90"][:9].max() < 100


def test_vertical_and_diagonal_neighbours_count_and_nan_reads_as_zero():
    ijk = np.array([[0, 0, 0], [1, 1, 1], [0, 0, 2]])
    v = np.array([np.nan, 2.0, 3.0])
    ctx = dict(zip(CONTEXT_CUE_NAMES, context_cues(_cues({"coverage_10cm": v}, 3), ijk).T))
    assert ctx["nb_count"].tolist() == [1, 2, 1]
    assert ctx["nb_max_coverage_10cm"].tolist() == [2.0, 3.0, 2.0]
    assert ctx["nb_mean_coverage_10cm"][1] == 1.5  # the NaN neighbour counts as 0


def test_with_context_appends_in_cue_name_order_and_order_does_not_matter():
    rng = np.random.default_rng(0)
    ijk = rng.integers(-3, 3, (40, 3))
    ijk = np.unique(ijk, axis=0)
    pc = rng.random((len(ijk), len(OWN_CUE_NAMES))).astype(np.float32)
    full = with_context(pc, ijk)
    assert full.shape == (len(ijk), len(CUE_NAMES))
    for j, name in enumerate(OWN_CUE_NAMES):  # every own cue lands in its named column
        np.testing.assert_array_equal(full[:, CUE_NAMES.index(name)], pc[:, j])
    perm = rng.permutation(len(ijk))
    np.testing.assert_allclose(with_context(pc[perm], ijk[perm]), full[perm], rtol=1e-6)
    assert with_context(np.zeros((0, len(OWN_CUE_NAMES))), np.zeros((0, 3), int)).shape == (0, len(CUE_NAMES))
    # the surface context: max / mean of the in-plane share over the neighbours
    lat = CUE_NAMES.index("surf_lateral_frac_10cm")
    nb_max = CUE_NAMES.index("nb_max_surf_lateral_frac_10cm")
    one = np.zeros((2, len(OWN_CUE_NAMES)), np.float32)
    one[0, OWN_CUE_NAMES.index("surf_lateral_frac_10cm")] = 0.7
    got = with_context(one, np.array([[0, 0, 0], [0, 1, 0]]))
    assert got[0, lat] == np.float32(0.7) and got[1, nb_max] == np.float32(0.7) and got[0, nb_max] == 0.0


def test_clean_context_copies_keep_the_own_cues_and_labels_and_take_a_clean_context():
    from ms3d_model.context import clean_context_copies

    rng = np.random.default_rng(1)
    n = 200
    cues = rng.random((n, len(CUE_NAMES))).astype(np.float32)
    labels = (rng.random(n) < 0.3).astype(np.int8)
    count, dirty = CUE_NAMES.index("nb_count"), CUE_NAMES.index("nb_max_p2m_frac_15cm")
    cues[:, count] = rng.integers(0, 9, n)
    out, lab = clean_context_copies(cues, labels, 0.25, seed=3)
    assert out.shape == (n + 50, len(CUE_NAMES)) and lab.shape == (n + 50,)
    np.testing.assert_array_equal(out[:n], cues)
    copies = out[n:]
    # each copy is some original pair's own cues with its label ...
    src = [int(np.flatnonzero((cues[:, :N_PAIR_CUES] == c[:N_PAIR_CUES]).all(1))[0]) for c in copies]
    np.testing.assert_array_equal(lab[n:], labels[src])
    # ... and the context of a good pair with >= 2 neighbours, none dirty
    donors = (labels == 0) & (cues[:, count] >= 2) & (cues[:, dirty] < 0.15)
    for c in copies:
        assert any((cues[d, CONTEXT_COLUMNS] == c[CONTEXT_COLUMNS]).all() for d in np.flatnonzero(donors))
    own = np.setdiff1d(np.arange(len(CUE_NAMES)), CONTEXT_COLUMNS)  # the surface cues are the pair's own too
    assert CUE_NAMES.index("surf_lateral_p90") in own
    for c, s in zip(copies, src):
        np.testing.assert_array_equal(c[own], cues[s, own])
    assert clean_context_copies(cues, labels, 0.0)[0] is cues
    assert clean_context_copies(cues[:, :N_PAIR_CUES], labels, 0.25)[0].shape == (n, N_PAIR_CUES)  # no context


def test_a_cell_off_the_mesh_against_its_neighbours_reads_in_the_relative_cues():
    """A dent: the middle cell's scan 5 cm in front of the mesh, its neighbours' on it."""
    own = np.zeros((3, len(OWN_CUE_NAMES)), np.float32)
    own[:, OWN_CUE_NAMES.index("p2m_signed_median")] = [0.0, 0.05, 0.0]
    got = dict(zip(CUE_NAMES, with_context(own, np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]])).T))
    np.testing.assert_allclose(got["around_p2m_signed_median"], [0.05, 0.0, 0.05], atol=1e-7)
    np.testing.assert_allclose(got["vs_around_p2m_signed_median"], [-0.05, 0.05, -0.05], atol=1e-7)
    alone = dict(zip(CUE_NAMES, with_context(own[:1], np.zeros((1, 3), int)).T))  # no neighbour: around is 0
    assert alone["around_p2m_signed_median"][0] == 0.0 and alone["vs_around_p2m_signed_median"][0] == 0.0
