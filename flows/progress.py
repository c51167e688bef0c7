"""Waiting for mapped Prefect futures, with a terminal progress bar (rich) when stderr is a terminal."""

from __future__ import annotations

from dataclasses import dataclass, field

from prefect.futures import as_completed


@dataclass
class Progress:
    """A progress bar over futures, silent when disabled."""

    label: str
    total: int
    enabled: bool = True
    _bar: object = field(default=None, repr=False)

    def __enter__(self):
        if self.enabled and self.total:
            from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn
            from rich.progress import Progress as Bar

            self._bar = Bar(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
            self._bar.start()
            self._id = self._bar.add_task(self.label, total=self.total)
        return self

    def advance(self):
        if self._bar is not None:
            self._bar.advance(self._id)

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.stop()


def wait_all(futures, label: str, progress: bool) -> list:
    """Wait for every future; return their final states in submission order."""
    with Progress(label, len(futures), enabled=progress) as bar:
        for _ in as_completed(futures):
            bar.advance()
    for f in futures:
        f.wait()  # sets the future's final state from the Dask result, not from the (lagging) API
    return [f.state for f in futures]
