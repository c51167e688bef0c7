"""The Parquet patch store (schema v2): one folder per tile, tables sorted by patch.

::

    tiles/{ix}_{iy}/points.parquet    MLS points, sorted by patch (one row per point)
    tiles/{ix}_{iy}/faces.parquet     mesh faces, 3 vertices inline, sorted by patch (one row per face)
    tiles/{ix}_{iy}/patches.parquet   one row per patch: ids, counts, row ranges, bbox
    tiles/{ix}_{iy}/labels.parquet    side table, one row per patch: ground-truth label (label stage)
    tiles/{ix}_{iy}/outliers.parquet  side table: count-outlier flags (outlier stage)
    tiles/{ix}_{iy}/grades.parquet    side table: score, grade (classify stage)

The partition output (points, faces, patches) is never rewritten by a later stage: labels, flags and
grades live in small side tables, aligned row for row with ``patches.parquet`` (same ``patch`` column;
a reader refuses a side table that does not match, so a stale one is never joined).

Coordinates are float32 metres, campus-local (offsets from the campus.json origin). ``patch`` is the
packed int64 key of :class:`storage.grid.PatchGrid` (world-anchored cells, so stable across runs and
campus extents); rows of patch p are ``point_start:point_stop`` / ``face_start:face_stop`` of the sorted
tables.

What v2 adds for the stages after partition:

- ``vid0, vid1, vid2`` (faces): a vertex id per corner, unique in the campus: ``source << 32 | vertex index``
  where ``source`` is the input file's stable id (:func:`storage.inputs.identity.source_id`) and the index is the
  file's vertex index after welding exactly coincident vertices (seam-split glTF/PLY vertices get one
  id). Faces of a patch or a region weld exactly, and edge neighbours are exact (a shared vertex-id pair).
- ``vp0, vp1, vp2`` (faces): the patch holding each corner vertex (the paper's Algorithm 1, step 3).
- ``nx, ny, nz`` (faces): unit face normal (right hand on v0 -> v1 -> v2), computed in float64 world
  coordinates before the cast.
- ``source`` is the stable uint32 input id (points and faces), not a list position.
- Point normals are not stored: they cost a k-NN PCA over every point (the fusion stage needs them
  only in bad regions, a fraction of the campus, and computes them there).

Every file carries Parquet key-value metadata ``ms3d`` = JSON ``{"schema_version", "table", "units",
"frame", "patch_size_m", "tile", "crs", "n_rows"}`` (+ ``"textures"`` in faces, + ``"points_rows"``,
``"faces_rows"`` in patches so a reader can tell the three files belong together). Files are written to a
temporary name and renamed; ``patches.parquet`` is removed first and written last, so its presence marks
a complete tile. Stores of schema v1 are refused with a message saying to re-run.

Missing optional input columns are written with documented defaults (:data:`POINT_DEFAULTS`,
:data:`FACE_DEFAULTS`): zeros for attributes, NaN for uv and normals, -1 for ``texture``, ``src_face``
and vertex ids. Unknown columns are rejected: the schema is fixed per ``schema_version``.

Compression ("auto"): coordinates, uv and gps_time are stored uncompressed (float32 mantissas of metre
offsets are close to random: lz4/zstd gain ~10 % and halve write speed); patch, source, texture and
classification are dictionary + RLE encoded; other integer attributes use lz4. Measured on 5 M MLS-like
points: ~0.7 s CPU to write, 163 MB; zstd everywhere 1.3 s, 113 MB. Pass ``compression="zstd"`` for
archival size.
"""
