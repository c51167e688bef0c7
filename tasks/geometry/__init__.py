"""Pure geometry several stages share (not a stage: it reads and writes no files).

- :mod:`tasks.geometry.triangles`: per-face unit normals and areas, area-weighted vertex normals;
- :mod:`tasks.geometry.sampling`: area-weighted, stratified, deterministic surface samples;
- :mod:`tasks.geometry.distance`: exact point-to-mesh distances;
- :mod:`tasks.geometry.cells`: rows grouped by patch cell (a stable sort by patch key);
- :mod:`tasks.geometry.tiling`: rows routed to ground tiles, boxes under a transform;
- :mod:`tasks.geometry.footprints`: building footprints of a mesh on a ground grid (raised cells, labelled).

Import from the modules; arrays in, arrays out (shapes and units in each docstring).
"""
