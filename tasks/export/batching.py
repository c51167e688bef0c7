"""How the flow maps the export's nodes: batches of about equal cost, jobs moved between work-dir mirrors, the
records put back in order. Pure: jobs in, batches and records out (:mod:`tasks.export.stage` runs them)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from storage import recorded
from storage.errors import InputError
from tasks.batches import balanced_batches
from tasks.export.nodes import NodeJob


def _node_cost(job) -> float:
    """A node's expected cost, to balance batches: a leaf's merged mesh bytes, a parent's children's faces
    (1 when unknown). Merged tiles differ a lot (92 to 2.4 M faces in the demo), so equal counts would not
    balance."""
    if not isinstance(job, NodeJob):
        return 1.0
    if job.tile_dir is not None:
        st = recorded.state(job.tile_dir / "merged.npz")  # on a bucket: the recorded size
        return float(st.size) if st is not None else 1.0
    return float(sum(rec.get("faces") or 0 for _, rec in job.children)) or 1.0


def node_batches(jobs: list[NodeJob], n_workers: int) -> list[list[tuple[int, NodeJob]]]:
    """The (index, job) batches the flow maps for one level of the quadtree: one node each up to 8 per
    worker (a leaf costs seconds, a task run ~0.3 s), else at most 8 per worker of about equal cost
    (:func:`_node_cost`), each in job order; the costliest first."""
    indexed = list(enumerate(jobs))
    return balanced_batches(indexed, [_node_cost(j) for j in jobs], 8 * n_workers)


def relocate_jobs(jobs: list[tuple[int, NodeJob]], old: Path, new: Path) -> list[tuple[int, NodeJob]]:
    """(index, job) pairs whose work-dir paths (``out``, ``cache``, ``tile_dir``) under ``old`` are moved under
    ``new``: jobs planned on one process's mirror of a work dir on a bucket, built on another's (``Path()`` for
    ``new`` or ``old``: paths relative to the work dir).

    >>> job = NodeJob(None, "fp", Path("/a/output"), Path("/a/export/lod"), None, None, Path("/a/tiles/1_2"))
    >>> moved = relocate_jobs([(0, job)], Path("/a"), Path())[0][1]
    >>> str(moved.out), str(moved.tile_dir), str(relocate_jobs([(0, moved)], Path(), Path("/b"))[0][1].cache)
    ('output', 'tiles/1_2', '/b/export/lod')
    """
    def move(p: Path | None) -> Path | None:
        return None if p is None else new / Path(p).relative_to(old)

    fields = ("out", "cache", "tile_dir")  # a PointsJob has no cache
    return [(i, replace(j, **{f: move(getattr(j, f)) for f in fields if hasattr(j, f)})) for i, j in jobs]


def node_records(results: list[dict], n_jobs: int) -> list[dict]:
    """The node records in job order from the flattened results of mapped :func:`build_nodes` (entries
    without an index, e.g. a task that failed whole, are ignored). Raises InputError (one line) when a
    node failed or is missing.

    >>> node_records([{"index": 1, "status": "done", "record": "b"}, {"index": 0, "status": "done", "record": "a"}], 2)
    ['a', 'b']
    """
    got = {r["index"]: r for r in results if "index" in r}
    bad = [r.get("error", "export task failed") for r in got.values() if r["status"] != "done"]
    if bad or len(got) != n_jobs:
        raise InputError(None, "; ".join(bad) or "an export task failed (see the run history)")
    return [got[i]["record"] for i in range(n_jobs)]
