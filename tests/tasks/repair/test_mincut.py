"""The compiled Boykov–Kolmogorov min-cut (tasks.repair.mincut): its cut is a minimum one (every cut of small
graphs enumerated), and, where the GPL PyMaxflow is installed (the ``gpl`` extra), the same flow and the same
cut to the node on random graphs and on the graphs the fusion and the view-selection tests build."""

import importlib.util
import itertools
from pathlib import Path

import numpy as np
import pytest

from tasks.repair import fuse, views
from tasks.repair.mincut import min_cut


def _random_graph(rng, n, rounded):
    m = int(rng.integers(0, 4 * n + 1))
    a, b = rng.integers(0, n, m), rng.integers(0, n, m)
    a, b = a[a != b], b[a != b]
    cs = rng.random(n) * (rng.random(n) < 0.5)
    ct = rng.random(n) * (rng.random(n) < 0.5)
    cap = rng.random(len(a)) * (rng.random(len(a)) < 0.7)
    rev = rng.random(len(a)) * (rng.random(len(a)) < 0.5)
    if rounded:  # ties: many cuts of the same value
        cs, ct, cap, rev = (np.round(x * 3) for x in (cs, ct, cap, rev))
    return cs, ct, a, b, cap, rev


def _cut_value(sink, cs, ct, a, b, cap, rev):
    return cs[sink].sum() + ct[~sink].sum() + cap[~sink[a] & sink[b]].sum() + rev[sink[a] & ~sink[b]].sum()


def test_the_cut_is_a_minimum_cut_and_its_value_the_flow():
    rng = np.random.default_rng(0)
    for t in range(300):
        n = int(rng.integers(1, 11))
        g = _random_graph(rng, n, t % 2 == 1)
        flow, sink = min_cut(*g)
        best = min(_cut_value(np.array(s, bool), *g) for s in itertools.product([False, True], repeat=n))
        assert abs(flow - best) <= 1e-9 * max(1.0, best)
        assert abs(_cut_value(sink, *g) - flow) <= 1e-9 * max(1.0, flow)
        if t % 2:  # among cuts of equal value: the sink side is the smallest one (the nodes that reach it)
            mins = [np.array(s, bool) for s in itertools.product([False, True], repeat=n)
                    if _cut_value(np.array(s, bool), *g) == best]
            assert all((sink <= s).all() for s in mins)


def test_an_empty_graph_and_a_graph_without_edges():
    assert min_cut(np.zeros(0), np.zeros(0), np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0))[0] == 0.0
    flow, sink = min_cut(np.array([1.0, 0.0, 2.0]), np.array([0.5, 3.0, 2.0]), np.zeros(0, int), np.zeros(0, int),
                         np.zeros(0), np.zeros(0))
    assert flow == 2.5 and sink.tolist() == [False, True, False]
    with pytest.raises(ValueError, match="unknown min_cut backend"):
        min_cut(np.ones(1), np.ones(1), np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0), backend="x")


def _same_as_pymaxflow(graphs):
    for g in graphs:
        f1, s1 = min_cut(*g)
        f2, s2 = min_cut(*g, backend="pymaxflow")
        assert f1 == f2 and (s1 == s2).all()


def test_random_graphs_cut_as_pymaxflow_cuts_them():
    pytest.importorskip("maxflow", reason="PyMaxflow (GPL, the gpl extra) not installed")
    rng = np.random.default_rng(1)
    _same_as_pymaxflow([_random_graph(rng, int(rng.integers(1, 80)), t % 2 == 1) for t in range(400)])


def _sibling(name):
    spec = importlib.util.spec_from_file_location(f"_mincut_{name}", Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_repair_tests_graphs_cut_as_pymaxflow_cuts_them(monkeypatch):
    """The graphs of tests/tasks/repair/test_fuse.py and test_texture.py's view selection, recorded."""
    pytest.importorskip("maxflow", reason="PyMaxflow (GPL, the gpl extra) not installed")
    test_fuse, test_texture = (_sibling(name) for name in ("test_fuse", "test_texture"))
    graphs = []

    def record(*g, backend="bk"):
        graphs.append(tuple(np.array(x) for x in g))
        return min_cut(*g, backend=backend)

    monkeypatch.setattr(fuse, "min_cut", record)
    monkeypatch.setattr(views, "min_cut", record)
    test_fuse.test_exactly_the_covered_vertices_are_replaced()
    test_fuse.test_points_far_in_front_of_the_mesh_are_rejected()
    test_fuse.test_forced_and_locked_vertices()
    test_texture.test_sparse_view_selection_takes_entries_in_any_order_and_needs_a_label_per_face()
    assert len(graphs) > 10 and max(len(g[0]) for g in graphs) > 2000
    _same_as_pymaxflow(graphs)
