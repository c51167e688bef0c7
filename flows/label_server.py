"""The labelling API of ``ms3d view WORKDIR --label`` (mounted by :mod:`flows.view` under ``/api/``).

    GET  /api/proposals?n=N  -> {"threshold", "proposals": [{"i", "j", "k", "score", "margin", "ecef": [x, y, z]}]}
                                the N graded patches whose score is closest to the operating threshold
                                (least sure first), not yet labelled by the user
    POST /api/locate          {"ecef": [x, y, z]} -> {"i", "j", "k", "ecef"}: the patch cell of a picked point
                                (the viewer sends the picked face's centroid: faces belong to the patch of
                                their centroid) and the ECEF centre of that cell
    POST /api/label           {"i", "j", "k", "label": 0|1} -> {"ok": true, "file", "n_labels"}
    GET  /api/labels          -> {"labels": [{"i", "j", "k", "label"}]}: the user's labels so far (latest wins)

Frames: the viewer works in the tileset's ECEF frame (3D Tiles root transform, EPSG:4978, metres); the work
dir in campus-local metres (``campus.json`` frame). ECEF -> campus-local inverts the export's georeference
(``output/georef.json``) by fixed-point iteration on its forward map (ENU differs from the projected grid by
grid convergence and scale error, ~1e-3, so each step gains three digits). Patch cells come from the
campus's :class:`storage.grid.PatchGrid` (``campus.json`` ``grid``, else the default grid).

Errors are data: every handler returns (HTTP status, JSON body); a bad request is 400 with one ``error`` line.
"""

from __future__ import annotations

import json
import math
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.grid import PatchGrid
from storage.patches.read import read_side_table
from storage.workdir.layout import WorkDir, campus_frame, read_campus
from storage.workdir.user_labels import append_user_label, parse_label_request, read_user_labels

MAX_PROPOSALS = 1000


def least_sure(keys: np.ndarray, scores: np.ndarray, threshold: np.ndarray | float, n: int) -> np.ndarray:
    """Indices of the ``n`` patches whose score lies closest to the threshold, least sure first.

    keys: (u,) int64 packed patch keys (ties are broken by key, so the order is reproducible);
    scores: (u,) float probability of bad, NaN for patches that are not graded (never proposed);
    threshold: scalar or (u,) per patch (each tile's grades record the one they were graded at).

    >>> least_sure(np.array([10, 11, 12, 13]), np.array([0.9, 0.45, np.nan, 0.52]), 0.5, 3).tolist()
    [3, 1, 0]
    """
    margin = np.abs(np.asarray(scores, np.float64) - np.asarray(threshold, np.float64))
    ok = np.flatnonzero(np.isfinite(margin))
    order = np.lexsort((np.asarray(keys)[ok], margin[ok]))
    return ok[order[: max(int(n), 0)]]


@dataclass
class LabelApi:
    """The labelling endpoints of one work dir (``output/georef.json`` needed for ECEF; ``campus.json``)."""

    work_dir: Path

    def __post_init__(self):
        wd = WorkDir(self.work_dir)
        doc = read_campus(wd)
        self.frame = campus_frame(doc)
        self.grid = PatchGrid(**doc["grid"]) if "grid" in doc else PatchGrid()
        self._projector = None
        self._georef_path = wd.georef_json

    @property
    def projector(self):
        """The export's campus-local -> ECEF map, rebuilt from ``output/georef.json`` (lazy: pyproj)."""
        if self._projector is None:
            from tasks.export import EnuProjector, make_georef

            try:
                g = json.loads(self._georef_path.read_text())
                ref = make_georef(g["source_crs"], g["frame_origin"], g["enu_origin_local"], g.get("vertical_datum"),
                                  g.get("geoid"))
            except (OSError, ValueError, KeyError) as exc:
                raise InputError(self._georef_path, f"cannot georeference the viewer's picks ({exc})") from None
            self._projector = (EnuProjector(ref), ref)
        return self._projector

    def local_to_ecef(self, local: np.ndarray) -> np.ndarray:
        """(n, 3) campus-local metres -> (n, 3) float64 ECEF metres."""
        return self.projector[0].local_to_ecef(np.asarray(local, np.float64).reshape(-1, 3))

    def ecef_to_local(self, ecef: np.ndarray, iterations: int = 4) -> np.ndarray:
        """(n, 3) ECEF metres -> (n, 3) float64 campus-local metres (inverse of :meth:`local_to_ecef`)."""
        proj, ref = self.projector
        ecef = np.asarray(ecef, np.float64).reshape(-1, 3)
        r = ref.ecef_to_enu_rotation
        local = (ecef - np.asarray(ref.ecef_origin)) @ r.T + np.asarray(ref.enu_origin_local)
        for _ in range(iterations):  # ENU ~ the projected grid: each step shrinks the error ~1000 times
            local += (ecef - proj.local_to_ecef(local)) @ r.T
        return local

    def proposals(self, n: int) -> dict:
        """The ``n`` least-sure graded patches of the live tiles that the user has not labelled yet."""
        wd = WorkDir(self.work_dir)
        keys, scores, thr = [], [], []
        for t in wd.live_tiles():
            got = read_side_table(wd.tile_dir(t), "grades")
            if got is None:
                continue
            cols, meta = got
            keys.append(cols["patch"])
            scores.append(cols["score"])
            thr.append(np.full(len(cols["patch"]), float(meta.get("threshold", 0.5))))
        if not keys:
            return {"threshold": None, "proposals": [], "note": "no grades: run the classify stage first"}
        keys, scores, thr = (np.concatenate(a) for a in (keys, scores, thr))
        done, _ = read_user_labels(self.work_dir)
        scores = np.where(np.isin(keys, done), np.nan, scores)
        pick = least_sure(keys, scores, thr, n)
        ijk = PatchGrid.unpack(keys[pick])
        centres = self.grid.centre_world(ijk) - self.frame.origin_array
        ecef = self.local_to_ecef(centres) if len(pick) else np.zeros((0, 3))
        rows = [{"i": int(a), "j": int(b), "k": int(c), "score": float(scores[p]),
                 "margin": float(abs(scores[p] - thr[p])), "ecef": [float(v) for v in e]}
                for (a, b, c), p, e in zip(ijk, pick, ecef)]
        return {"threshold": float(np.median(thr)), "proposals": rows}

    def locate(self, body: bytes) -> dict:
        """The patch cell of a picked ECEF point (``{"ecef": [x, y, z]}``); ValueError on a bad body."""
        try:
            xyz = json.loads(body.decode("utf-8"))["ecef"]
            xyz = [float(v) for v in xyz]
        except (UnicodeDecodeError, ValueError, KeyError, TypeError):
            raise ValueError('body must be {"ecef": [x, y, z]} (numbers, metres)') from None
        if len(xyz) != 3 or not all(math.isfinite(v) for v in xyz):
            raise ValueError("ecef must be three finite numbers")
        world = self.frame.to_world(self.ecef_to_local(np.array([xyz])))
        try:
            ijk = self.grid.cells_world(world)
            i, j, k = (int(v) for v in ijk[0])
        except ValueError as exc:
            raise ValueError(f"the point is outside the patch grid ({exc})") from None
        centre = self.local_to_ecef(self.grid.centre_world(ijk) - self.frame.origin_array)[0]
        return {"i": i, "j": j, "k": k, "ecef": [float(v) for v in centre]}

    def label(self, body: bytes) -> dict:
        ijk, lab = parse_label_request(body)
        path = append_user_label(self.work_dir, ijk, lab)
        return {"ok": True, "file": str(path.relative_to(self.work_dir)), "n_labels": len(read_user_labels(self.work_dir)[0])}

    def labels(self) -> dict:
        keys, labs = read_user_labels(self.work_dir)
        return {"labels": [{"i": int(a), "j": int(b), "k": int(c), "label": int(v)}
                           for (a, b, c), v in zip(PatchGrid.unpack(keys), labs)]}

    def handle(self, method: str, url: str, body: bytes = b"") -> tuple[int, dict]:
        """One request -> (HTTP status, JSON body). Never raises for bad input: 400 and one ``error`` line."""
        parts = urllib.parse.urlsplit(url)
        route = (method, parts.path)
        try:
            if route == ("GET", "/api/proposals"):
                q = urllib.parse.parse_qs(parts.query)
                try:
                    n = int(q.get("n", ["20"])[0])
                except ValueError:
                    raise ValueError("n must be an integer") from None
                return 200, self.proposals(min(max(n, 0), MAX_PROPOSALS))
            if route == ("GET", "/api/labels"):
                return 200, self.labels()
            if route == ("POST", "/api/label"):
                return 200, self.label(body)
            if route == ("POST", "/api/locate"):
                return 200, self.locate(body)
        except ValueError as exc:
            return 400, {"error": str(exc)}
        except InputError as exc:
            return 500, {"error": str(exc)}
        return 404, {"error": f"no such endpoint: {method} {parts.path}"}
