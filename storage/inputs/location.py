"""Where an input lives: one type for a local path and an object-store URL, in the spirit of mapchete's
``MPath``. Every "is this a URL?" question in ms3d is :func:`is_url`; path arithmetic that must work on
both (parent folder, name, joining) is :class:`Location`.

>>> is_url("s3://bucket/a.laz"), is_url("/data/a.laz"), is_url("file:///data/a.laz")
(True, False, False)
>>> loc = Location("s3://bucket/prod/Data/Tile_+000_+000/Tile_+000_+000.obj")
>>> loc.parent.name, str(loc.parent.parent / "metadata.xml")
('Tile_+000_+000', 's3://bucket/prod/Data/metadata.xml')
>>> Location("/data/prod/metadata.xml").parent.name
'prod'
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path, PurePosixPath

URL_SCHEMES = ("s3://", "s3a://")


def is_url(path) -> bool:
    """Whether ``path`` names an object-store input (``file://`` and plain paths are local)."""
    return isinstance(path, str) and path.startswith(URL_SCHEMES)


@dataclass(frozen=True)
class Location:
    """A local path or an object URL (``raw``, as the user named it); immutable, comparable, hashable."""

    raw: str

    def __init__(self, raw: str | Path | Location):
        object.__setattr__(self, "raw", raw.raw if isinstance(raw, Location) else str(raw))

    @property
    def is_url(self) -> bool:
        return is_url(self.raw)

    def _split(self) -> tuple[str, str]:
        """(scheme + bucket, key) of a URL; ("", path) of a local path."""
        if not self.is_url:
            return "", self.raw
        scheme, _, rest = self.raw.partition("://")
        bucket, _, key = rest.partition("/")
        return f"{scheme}://{bucket}", key

    @property
    def name(self) -> str:
        return PurePosixPath(self._split()[1]).name if self.is_url else Path(self.raw).name

    @property
    def parent(self) -> Location:
        if not self.is_url:
            return Location(Path(self.raw).parent)
        bucket, key = self._split()
        head = key.rstrip("/").rpartition("/")[0]
        return Location(f"{bucket}/{head}" if head else bucket)

    def __truediv__(self, name: str) -> Location:
        return Location(f"{self.raw.rstrip('/')}/{name}" if self.is_url else Path(self.raw) / name)

    @property
    def path(self) -> Path:
        """The local path (ValueError for a URL: stage it first, :func:`storage.inputs.remote.local_input`)."""
        if self.is_url:
            raise ValueError(f"{self.raw} is a URL, not a local path")
        return Path(self.raw)

    def __str__(self) -> str:
        return self.raw


EMBEDDED_CONTAINERS = (".glb", ".gltf", ".3mxb", ".b3dm")


def split_embedded(ref) -> tuple[str, str] | None:
    """(container path, image key) of a reference to an image embedded in a mesh container
    (``<file.glb>#image0``; :mod:`storage.formats.embedded`), or None for an ordinary path.

    >>> split_embedded("/d/a.glb#image0"), split_embedded("/d/t.jpg")
    (('/d/a.glb', 'image0'), None)
    """
    s = str(ref)
    head, sep, key = s.rpartition("#")
    if not sep or not key or "/" in key or PurePosixPath(head).suffix.lower() not in EMBEDDED_CONTAINERS:
        return None
    return head, key
