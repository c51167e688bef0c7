"""Named numpy arrays in one ``.npz`` (uncompressed): the caches and intermediate arrays of a stage.

    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "a.npz"
    >>> write_arrays(p, {"x": np.arange(3), "name": np.array("tile")})
    >>> got = read_arrays(p)
    >>> got["x"].tolist(), str(got["name"])
    ([0, 1, 2], 'tile')
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.atomic import atomic_path


def write_arrays(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` as one .npz, atomically (a reader never sees half a file); creates the folder."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def read_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of a .npz, read whole (no pickled objects)."""
    with np.load(path, allow_pickle=False) as z:
        return {name: z[name] for name in z.files}


__all__ = ["read_arrays", "write_arrays"]
