"""Errors that are part of ms3d's interface.

Every problem with an input file raises :class:`InputError` naming the file and what is wrong, so a
failed tile reports something a surveyor can act on ("points.laz: truncated after 1,204,000 of
2,000,000 points") rather than a stack trace from deep inside a reader.
"""

from __future__ import annotations

from pathlib import Path


class Ms3dError(Exception):
    """Base class of ms3d's own errors."""


class InputError(Ms3dError):
    """A bad input: corrupt, truncated, empty, NaN coordinates, wrong CRS/units, missing texture...

    Args:
        path: the offending file (or folder); may be None for in-memory inputs.
        problem: one sentence saying what is wrong.
    """

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)

    def __reduce__(self):  # picklable across Dask workers
        return (type(self), (self.path, self.problem))


class EmptyTileError(InputError):
    """A tile that holds no data of the kind a stage needs (mapchete's 'empty' signal)."""
