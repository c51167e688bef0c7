"""Figures of the run report: the class map (top view of patches) and renders of rebuilt regions.

Pure functions over arrays that return PNG bytes (matplotlib's Agg canvas, no pyplot state, so they are
safe in worker threads). Renders are orthographic, flat-shaded by the angle between each face normal and
the view direction, rasterised with a depth buffer by a compiled loop (millions of triangles in a
second).
"""

from __future__ import annotations

import io
import math

import numpy as np
from numba import njit

GRADE_COLOURS = {-1: (0.75, 0.75, 0.75), 0: (0.30, 0.65, 0.35), 1: (0.85, 0.25, 0.20)}
REBUILT_COLOUR = np.array([0.95, 0.60, 0.15])
MESH_COLOUR = np.array([0.78, 0.78, 0.80])
BAD_COLOUR = np.array([0.90, 0.35, 0.30])
MAX_MAP_PX = 2000


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _figure(w_in: float, h_in: float, dpi: int = 100):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w_in, h_in), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def column_raster(i: np.ndarray, j: np.ndarray, value: np.ndarray, reduce: str = "max",
                  max_px: int = MAX_MAP_PX) -> tuple[np.ndarray, tuple[int, int], int]:
    """Patch columns (i, j) -> a 2D raster of ``value`` reduced over k (and over binned columns).

    i, j: (n,) int64 patch cells; value: (n,) float (NaN = no value). reduce: "max" (worst score or
    grade). Returns (raster (rows, cols) float64, NaN where empty, row 0 = lowest j; (i0, j0) the cell of
    pixel (0, 0); bin: cells per pixel side, so the raster is at most ``max_px`` a side).

    >>> r, origin, b = column_raster(np.array([5, 5, 6]), np.array([2, 2, 3]), np.array([0.1, 0.7, 0.2]))
    >>> r.tolist(), origin, b
    ([[0.7, nan], [nan, 0.2]], (5, 2), 1)
    """
    if reduce != "max":
        raise ValueError(f"unknown reduction {reduce!r}")
    i0, j0 = int(i.min()), int(j.min())
    span = max(int(i.max()) - i0, int(j.max()) - j0) + 1
    b = max(1, math.ceil(span / max_px))
    c, r = (i - i0) // b, (j - j0) // b
    raster = np.full((int(r.max()) + 1, int(c.max()) + 1), -np.inf)
    ok = np.isfinite(value)
    np.maximum.at(raster, (r[ok], c[ok]), value[ok])
    raster[raster == -np.inf] = np.nan
    return raster, (i0, j0), b


def class_map_png(i: np.ndarray, j: np.ndarray, value: np.ndarray, kind: str, cell_xy_m: tuple[float, float],
                  corner_xy_m: tuple[float, float], title: str) -> bytes:
    """Top view of patch columns coloured by score (kind "score": 0 good .. 1 bad, worst over the column)
    or grade (kind "grade": -1 unknown, 0 good, 1 bad). cell_xy_m: patch size in x/y; corner_xy_m:
    campus-local x/y of cell (0, 0)'s corner (anchor - origin), so the axes are campus-local metres."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    raster, (i0, j0), b = column_raster(i, j, value)
    x0 = corner_xy_m[0] + i0 * cell_xy_m[0]
    y0 = corner_xy_m[1] + j0 * cell_xy_m[1]
    extent = (x0, x0 + raster.shape[1] * b * cell_xy_m[0], y0, y0 + raster.shape[0] * b * cell_xy_m[1])
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    fig = _figure(9, max(3.0, min(9.0, 9 * aspect + 1)))
    ax = fig.add_subplot(1, 1, 1)
    if kind == "score":
        im = ax.imshow(raster, origin="lower", extent=extent, cmap="RdYlGn_r", vmin=0, vmax=1,
                       interpolation="nearest")
        fig.colorbar(im, ax=ax, label="score (worst in the column): 0 good, 1 bad", shrink=0.8)
    else:
        cmap = ListedColormap([GRADE_COLOURS[-1], GRADE_COLOURS[0], GRADE_COLOURS[1]])
        ax.imshow(raster + 1, origin="lower", extent=extent, cmap=cmap, vmin=-0.5, vmax=2.5, interpolation="nearest")
        ax.legend(handles=[Patch(color=GRADE_COLOURS[g], label=n) for g, n in ((0, "good"), (1, "bad"), (-1, "unknown"))],
                  loc="upper right", fontsize=8)  # fmt: skip
    ax.set_xlabel("x (m, campus-local)")
    ax.set_ylabel("y (m, campus-local)")
    ax.set_aspect("equal")
    ax.set_title(title)
    fig.tight_layout()
    return _png(fig)


def view_basis(normals: np.ndarray, elevation_deg: float = 25.0) -> np.ndarray:
    """(3, 3) rows right, up, forward of an orthographic camera looking at surfaces with mean outward
    ``normals`` (k, 3) from the front and ``elevation_deg`` above; straight down when they face up."""
    n = np.asarray(normals, np.float64).mean(axis=0) if len(normals) else np.zeros(3)
    h = np.array([n[0], n[1], 0.0])
    if np.linalg.norm(h) < 0.2 * max(abs(n[2]), 1e-9):  # roofs and ground: from above, a little tilted
        h, elevation_deg = np.array([0.0, 1.0, 0.0]), 70.0
    h /= np.linalg.norm(h)
    e = math.radians(elevation_deg)
    forward = -h * math.cos(e) - np.array([0, 0, 1.0]) * math.sin(e)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return np.stack([right, up, forward])


RENDER_PX = 800  # long side of a region render's raster, per panel


def rasterise(xy: np.ndarray, depth: np.ndarray, rgb: np.ndarray, lo: np.ndarray, hi: np.ndarray,
              px: int = RENDER_PX) -> np.ndarray:
    """Flat triangles into an image with a depth buffer (the nearest face wins at each pixel centre).

    xy: (m, 3, 2) float64 corners in view metres; depth: (m,) float64 along the view (smaller is nearer);
    rgb: (m, 3) float in [0, 1]; lo, hi: (2,) the window. Returns (H, W, 4) float RGBA (alpha 0 where no face
    covers the pixel's centre), row 0 at ``lo[1]``, the long side ``px`` pixels.

    >>> img = rasterise(np.array([[[0., 0], [4, 0], [0, 4]]]), np.zeros(1), np.array([[1., 0, 0]]),
    ...                 np.zeros(2), np.array([4., 4]), px=4)
    >>> img[..., 3].astype(int).tolist()
    [[1, 1, 1, 1], [1, 1, 1, 0], [1, 1, 0, 0], [1, 0, 0, 0]]
    """
    span = np.maximum(np.asarray(hi, np.float64) - lo, 1e-9)
    step = float(span.max()) / px
    w, h = (max(int(v), 1) for v in np.ceil(span / step))
    p = (np.asarray(xy, np.float64) - lo) / step - 0.5  # pixel (c, r) has its centre at (c, r) here
    bad = ~(np.isfinite(p).all(axis=(1, 2)) & np.isfinite(depth))
    p[bad] = -1.0  # a face with a NaN corner or depth covers no pixel (its box is empty)
    face = _nearest_faces(p, np.asarray(depth, np.float64), w, h)  # compiled: one pass over the faces
    img = np.zeros((w * h, 4))
    hit = face >= 0
    img[hit, :3], img[hit, 3] = np.asarray(rgb, np.float64)[face[hit]], 1.0
    return img.reshape(h, w, 4)


@njit(cache=True, nogil=True)
def _nearest_faces(p: np.ndarray, depth: np.ndarray, w: int, h: int) -> np.ndarray:
    """(h * w,) int64: at each pixel centre (c, r), the face of ``p`` (m, 3, 2) float64 (pixel coordinates;
    NaN corners cover nothing) covering it (edges included, either winding) with the smallest ``depth``
    (m,) (the lower index on a tie); -1 where none does."""
    zbuf = np.full(w * h, np.inf)
    face = np.full(w * h, -1, np.int64)
    for t in range(len(p)):
        xs, ys = p[t, :, 0], p[t, :, 1]
        if not (np.isfinite(xs).all() and np.isfinite(ys).all() and np.isfinite(depth[t])):
            continue
        x0 = int(min(max(math.ceil(xs.min()), 0.0), w))  # clamped as floats first: no huge ints
        x1 = int(max(min(math.floor(xs.max()), w - 1.0), -1.0))
        y0 = int(min(max(math.ceil(ys.min()), 0.0), h))
        y1 = int(max(min(math.floor(ys.max()), h - 1.0), -1.0))
        for r in range(y0, y1 + 1):
            for c in range(x0, x1 + 1):
                pos = neg = 0
                for i in range(3):
                    j = (i + 1) % 3
                    e = (xs[j] - xs[i]) * (r - ys[i]) - (ys[j] - ys[i]) * (c - xs[i])
                    pos += e >= 0
                    neg += e <= 0
                pix = r * w + c
                if (pos == 3 or neg == 3) and depth[t] < zbuf[pix]:
                    zbuf[pix], face[pix] = depth[t], t
    return face


def render_png(panels: list[tuple[str, np.ndarray, np.ndarray]], basis: np.ndarray, title: str,
               size_in: float = 4.5) -> bytes:
    """Panels side by side, one camera: each (caption, triangles (m, 3, 3) float metres, colours (m, 3)
    float RGB in [0, 1]). Flat shading by |cos| between face normal and view direction; each panel is
    rasterised with a depth buffer (:func:`rasterise`), so millions of faces cost seconds, not minutes."""
    fig = _figure(size_in * len(panels), size_in + 0.4)
    pts = [tri.reshape(-1, 3) @ basis[:2].T for _, tri, _ in panels if len(tri)]
    lo = np.min([p.min(axis=0) for p in pts], axis=0) if pts else np.zeros(2)
    hi = np.max([p.max(axis=0) for p in pts], axis=0) if pts else np.ones(2)
    pad = 0.04 * float(max(hi - lo)) + 1e-3
    lo, hi = lo - pad, hi + pad
    for n, (caption, tri, colour) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), n + 1)
        if len(tri):
            tri = np.asarray(tri, np.float64)
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
            shade = 0.35 + 0.65 * np.abs(normal @ basis[2])
            rgb = np.clip(np.asarray(colour, np.float64) * shade[:, None], 0, 1)
            img = rasterise(tri @ basis[:2].T, tri.mean(axis=1) @ basis[2], rgb, lo, hi)
            ax.imshow(img, origin="lower", extent=(lo[0], lo[0] + img.shape[1] * (hi - lo).max() / RENDER_PX,
                                                    lo[1], lo[1] + img.shape[0] * (hi - lo).max() / RENDER_PX),
                      interpolation="antialiased")
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"{caption} ({len(tri):,} faces)", fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def score_histogram_png(counts: np.ndarray, threshold: float = 0.5) -> bytes:
    """Bar chart of patch counts per score bin: counts (b,) int over b equal bins of [0, 1] (the network's
    probability of "bad"), bars at or above ``threshold`` coloured bad, below good."""
    counts = np.asarray(counts)
    edges = np.linspace(0.0, 1.0, len(counts) + 1)
    mid = (edges[:-1] + edges[1:]) / 2
    fig = _figure(7, 3.2)
    ax = fig.add_subplot(1, 1, 1)
    colours = [GRADE_COLOURS[1] if m >= threshold else GRADE_COLOURS[0] for m in mid]
    ax.bar(mid, counts, width=edges[1] - edges[0], color=colours, edgecolor="white", linewidth=0.5)
    ax.axvline(threshold, color="k", linestyle="--", linewidth=1)
    ax.set_xlim(0, 1)
    ax.set_xlabel("score (probability of bad)")
    ax.set_ylabel("graded patches")
    ax.set_title(f"{int(counts.sum()):,} graded patches; threshold {threshold:g}")
    fig.tight_layout()
    return _png(fig)
