"""The production a mesh input belongs to, whether it is named by a local path or by a URL: the one rule is
:func:`storage.formats.production.production_root_of`; here it is asked of the disk or of the bucket."""

from __future__ import annotations

from pathlib import Path

from storage.formats import production as local
from storage.formats.production import Production
from storage.inputs.location import is_url
from storage.inputs.remote import remote_production_of, remote_production_root


def production_root(mesh_path: str | Path) -> Path | str | None:
    """The production root of a mesh file (a URL for a URL), or None for an ordinary file."""
    return remote_production_root(mesh_path) if is_url(mesh_path) else local.production_root(mesh_path)


def production_of(mesh_path: str | Path) -> Production | None:
    """The :class:`Production` of a mesh file, local or by URL (its metadata read), or None for an ordinary
    file. InputError (naming ``metadata.xml``) when the metadata exists but cannot be used."""
    return remote_production_of(mesh_path) if is_url(mesh_path) else local.production_of(mesh_path)
