"""ms3d.storage: on-disk contracts (readers/writers, patch store, work dir, manifest)."""

__version__ = "0.1.0"
