"""Synthetic campus presets: sizes, densities and defect rates per preset."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SynthPreset:
    """extent_m: campus side lengths (x, y); tile_m: generation tile (bounded memory);
    mls_density_scale: multiplies the scanner's point rate (1.0 = RIEGL VMX-450-like, ~4,000 pts/m^2
    at 10 m); image_every_m: camera spacing along the trajectory (0 = no images); production_tile_m: the
    ContextCapture tile grid the mesh is cut on (``mesh/Data/Tile_*/``, :mod:`synth.production`; 0 = one
    ``mesh/mvs.obj``, or with ``tiled_mesh`` one folder per generation tile); lod_tile: a production tile that
    also gets a coarser level of detail (readers keep the finest; off in the presets while the quality stage
    reads every file of the mesh folder as the input mesh); coarse_passage_p: with ``--coarse-mesh``, each
    building's chance of a ground-floor through-passage (:mod:`synth.passages`; without it, none)."""

    name: str
    extent_m: tuple[float, float]
    n_buildings: int
    storeys: tuple[int, int]
    tile_m: float
    mls_density_scale: float
    n_passes: int
    image_every_m: float
    image_size: tuple[int, int]
    mvs_edge_m: float = 0.12
    tiled_mesh: bool = False
    production_tile_m: float = 0.0
    lod_tile: str | None = None
    coarse_passage_p: float = 1.0


PRESETS = {
    # one small building beside one road: seconds, for tests
    "tiny": SynthPreset("tiny", (60.0, 50.0), 1, (2, 4), 60.0, 0.04, 2, 25.0, (240, 180), mvs_edge_m=0.15,
                        production_tile_m=50.0),
    # 4-8 buildings along three streets near real street-MLS density (~15 M points): the demo campus
    "demo": SynthPreset("demo", (200.0, 100.0), 6, (1, 12), 200.0, 0.1, 2, 15.0, (1024, 768),
                        production_tile_m=100.0),
    # >= 0.25 km^2, >= 40 buildings, ~1e8 points, generated tile by tile in bounded memory
    "campus": SynthPreset("campus", (520.0, 520.0), 44, (1, 12), 130.0, 0.06, 2, 0.0, (1024, 768),
                          tiled_mesh=True),
}


def get_preset(name: str, scale: float = 1.0, mls_density: float | None = None) -> SynthPreset:
    """The named preset; ``scale`` multiplies the campus side lengths (and the building count);
    ``mls_density`` replaces the scanner rate as a fraction of the real one (1.0 = a RIEGL VMX-450's
    ~4,000 pts/m^2 on a wall at 10 m; the presets use 0.04-0.1 so tests and the demo stay quick)."""
    from dataclasses import replace

    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    p = PRESETS[name]
    if mls_density is not None:
        if not 0 < mls_density <= 4:
            raise ValueError(f"mls_density must be in (0, 4] (1.0 = the real scanner), got {mls_density}")
        p = replace(p, mls_density_scale=float(mls_density))
    if scale == 1.0:
        return p
    return replace(p, extent_m=(p.extent_m[0] * scale, p.extent_m[1] * scale),
                   n_buildings=max(1, int(round(p.n_buildings * scale * scale))))
