"""The stages' declarations (``tasks.stages``): every stage package declares itself, exports every name of
its ``__all__`` (lazily), stays light to import, and the flow's tasks carry the declarations."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from tasks.stages import BatchContext, StageSpec, balanced_region_batches, lazy_exports, one_per_task

ROOT = Path(__file__).resolve().parents[2]
STAGES = sorted(p.parent.name for p in (ROOT / "tasks").glob("*/__init__.py")
                if p.parent.name not in ("config", "geometry"))


@pytest.mark.parametrize("pkg", STAGES)
def test_every_exported_name_resolves(pkg):
    mod = importlib.import_module(f"tasks.{pkg}")
    missing = [n for n in mod.__all__ if not hasattr(mod, n)]
    assert not missing, f"tasks.{pkg} exports names it cannot give: {missing}"
    with pytest.raises(AttributeError):
        mod.no_such_name  # noqa: B018


def test_importing_the_declarations_loads_no_heavy_module():
    code = ("import sys, flows.tasks\n"
            "print(sorted(m for m in ('torch', 'open3d', 'numba', 'trimesh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_the_flow_tasks_carry_their_stage_declarations():
    from flows import tasks

    found = {t.spec.name: t for t in (getattr(tasks, n) for n in dir(tasks)) if isinstance(getattr(t, "spec", None),
                                                                                            StageSpec)}
    assert set(found) == {"scan", "register", "ingest", "partition", "outliers", "classify", "regions", "repair",
                          "merge", "export-nodes", "quality", "holdout", "region renders", "report"}
    assert all(t.name == name for name, t in found.items())  # the Prefect task is named by its stage
    assert found["export-nodes"].spec.priority > 0 > found["region renders"].spec.priority
    assert found["merge"].spec.reads_for(["1_2"]) == ("manifest.d/merge/", "campus.json", "regions/", "tiles/1_2/")
    assert found["regions"].spec.reads_for(["1_2"]) is None and "staging/" in found["regions"].spec.skips


def test_batching_rules():
    ctx = BatchContext(2, tiles_per_task=2, weights={"a": 1.0, "b": 5.0, "c": 3.0})
    assert one_per_task(["a", "b"], ctx) == [["a"], ["b"]]
    assert balanced_region_batches(["a", "b", "c"], ctx) == [["b"], ["c"], ["a"]]  # one each, heaviest first
    get = lazy_exports("pkg", {"os.path": "join sep=sep"})
    assert get("join")("a", "b") == "a/b" and get("sep") == "/"
    with pytest.raises(AttributeError, match="no attribute 'other'"):
        get("other")


def test_region_batches_are_spatially_coherent_and_sized_by_the_workers():
    """Regions on a 12 x 12 cell grid, given in shuffled order: each batch is a compact block of cells (its
    regions share tiles), the batches are about equal in weight, and their count follows the workers."""
    import numpy as np

    from storage.grid import PatchGrid
    from tasks.regions.plan import region_key

    cells = [(i, j, 0) for i in range(12) for j in range(12)]
    keys = [region_key(PatchGrid.pack(np.array([c]))) for c in cells]
    rng = np.random.default_rng(0)
    order = [keys[i] for i in rng.permutation(len(keys))]
    for workers in (2, 4):
        batches = balanced_region_batches(order, BatchContext(workers))
        assert len(batches) == 4 * workers and sorted(k for b in batches for k in b) == sorted(keys)
        assert max(map(len, batches)) - min(map(len, batches)) <= 1
        where = {k: c for k, c in zip(keys, cells)}
        for b in batches:  # a Hilbert run of n cells spans about sqrt(n) cells each way, never the campus
            ij = np.array([where[k][:2] for k in b])
            assert np.ptp(ij, axis=0).max() <= 2 * np.ceil(np.sqrt(len(b))), b
