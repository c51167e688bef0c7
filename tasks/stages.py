"""What the flow needs to know about a stage, declared once in the stage's own package (``STAGE`` in its
``__init__``): the flow iterates over these declarations and keeps no table of its own.

- ``unit``: what one manifest unit of the stage is ("file", "ingest unit", "tile", "campus", "region",
  "node", "share");
- ``batch``: how the units that must run become task runs (a task run costs ~0.3 s here: units are batched),
  a function of (units, :class:`BatchContext`) -> batches;
- ``reads``: the work-dir prefixes one task reads ("{tile}" once per tile of its batch); None for all but
  ``skips``;
- ``duration``: Dask's first guess of one task's duration, before it has timed one (Dask assumes 0.5 s; a
  long task guessed short makes the scheduler queue every one on one worker);
- ``priority``: the Dask priority of its tasks (higher first among queued tasks).

>>> spec = StageSpec("merge", "tile", fixed_tile_batches, reads=("tiles/{tile}/",))
>>> spec.reads_for(["1_2", "3_4"]), spec.batch([1, 2, 3], BatchContext(2, tiles_per_task=2))
(('tiles/1_2/', 'tiles/3_4/'), [[1, 2], [3]])
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from tasks.batches import fixed_batches


@dataclass(frozen=True)
class BatchContext:
    """What a batching rule may use: the worker count, ``cluster.tiles_per_task``, and per-unit weights
    (``{unit: weight}``: the regions' bytes, the tiles' store sizes) when the flow has them."""

    n_workers: int
    tiles_per_task: int = 1
    weights: dict = field(default_factory=dict)


def fixed_tile_batches(units: list, ctx: BatchContext) -> list[list]:
    """``cluster.tiles_per_task`` consecutive units per task."""
    return fixed_batches(units, ctx.tiles_per_task)


def largest_first_tile_batches(units: list, ctx: BatchContext) -> list[list]:
    """The units by weight (their store's size), largest first (ties in key order), then
    ``cluster.tiles_per_task`` per task: the longest units start first and the short ones fill the end."""
    return fixed_batches(sorted(units, key=lambda k: -ctx.weights.get(k, 0)), ctx.tiles_per_task)


def balanced_region_batches(units: list, ctx: BatchContext) -> list[list]:
    """``4 * n_workers`` batches of about equal weight (the regions' bytes), heaviest first, each a run of
    regions adjacent along a Hilbert curve through their first patch's cell (:func:`region_cell`): a batch's regions share
    tiles, so a worker reads each tile's stores for several of its regions, not each region's from
    another corner of the campus. n_workers: the cluster's task slots when the flow knows them. Units
    that are no region keys keep their order."""
    from tasks.batches import contiguous_batches, hilbert_index

    cells = {k: region_cell(k) for k in units}
    order = sorted(units, key=lambda k: (hilbert_index(*cells[k]) if cells[k] else -1))
    return contiguous_batches(order, [ctx.weights.get(k, 1.0) for k in order], 4 * ctx.n_workers)


def region_cell(key) -> tuple[int, int] | None:
    """(i, j) >= 0: the biased grid cell of a region key's first patch ("r" + 16 hex digits of its smallest
    patch key, :func:`tasks.regions.plan.region_key`); None for another unit."""
    if not (isinstance(key, str) and len(key) == 17 and key[0] == "r"):
        return None
    try:
        v = int(key[1:], 16)
    except ValueError:
        return None
    from storage.grid import PatchGrid

    i, j, _ = PatchGrid.unpack([v - (1 << 64) if v >= 1 << 63 else v])[0]
    return int(i) + (1 << 24), int(j) + (1 << 25)


def one_per_task(units: list, ctx: BatchContext) -> list[list]:
    """One unit per task (a unit long enough to be worth its task run)."""
    return [[u] for u in units]


@dataclass(frozen=True)
class StageSpec:
    """One stage as the flow sees it (module doc)."""

    name: str
    unit: str
    batch: Callable[[list, BatchContext], list[list]] = one_per_task
    reads: tuple[str, ...] | None = None
    skips: tuple[str, ...] = ()
    duration: str | None = None
    priority: int = 0

    def reads_for(self, batch: list) -> tuple[str, ...] | None:
        """The work-dir prefixes a task of this stage reads for ``batch`` (None: all but ``skips``)."""
        if self.reads is None:
            return None
        out: list[str] = []
        for p in self.reads:
            out += [p.format(tile=k) for k in batch] if "{tile}" in p else [p]
        return tuple(out)

    def __repr__(self) -> str:
        return f"StageSpec({self.name!r}, unit={self.unit!r}, batch={self.batch.__name__})"


# What a task that pulls the whole work dir never reads: the ingest runs (``staging/``, the largest part of a
# work dir: only partition and the driver's planning read them) and what the export writes.
CAMPUS_WIDE_SKIPS = ("staging/", "export/", "output/")

__all__ = ["CAMPUS_WIDE_SKIPS", "BatchContext", "StageSpec", "balanced_region_batches", "fixed_tile_batches", "lazy_exports",
           "largest_first_tile_batches", "one_per_task"]


def lazy_exports(package: str, modules: dict[str, str]) -> Callable[[str], object]:
    """A package's module ``__getattr__`` (PEP 562) that imports each exported name from its module on first
    use: ``{module: "name name ..."}`` (``alias=name`` for a name exported under another). A stage package then
    costs nothing to import for its ``STAGE`` (the flow's Prefect tasks import every stage's declaration), and a
    Dask worker loads only the modules of the tasks it runs (torch, open3d and numba are hundreds of MB).

    >>> get = lazy_exports("pkg", {"math": "pi tau=pi"})
    >>> get("pi") == get("tau") == 3.141592653589793
    True
    """
    import importlib

    where = {}
    for module, names in modules.items():
        for n in names.split():
            alias, _, attr = n.partition("=")
            where[alias] = (module, attr or alias)

    def __getattr__(name: str):
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module, attr = where[name]
        return getattr(importlib.import_module(module), attr)

    return __getattr__
