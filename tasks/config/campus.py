"""Typed run configuration (pydantic), loaded from YAML and overridable from the CLI.

Every parameter the paper names carries the paper's value in its description.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from storage.errors import InputError
from storage.grid import PatchGrid
from storage.inputs.location import is_url
from tasks.config.classify import ClassifyConfig
from tasks.config.repair import RepairConfig
from tasks.geometry.holdout import Holdout


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class InputsConfig(_Model):
    mesh: list[str] = Field(default_factory=list, description="mesh files or folders (OBJ+MTL / PLY / GLB); a folder is read as ContextCapture-style tiles")
    points: list[str] = Field(default_factory=list, description="MLS point clouds (LAS / LAZ / COPC / PLY / PCD / XYZ / E57)")
    points_bounds: tuple[float, float, float, float] | Literal["mesh"] | None = Field(None, description="[xmin, ymin, xmax, ymax] world metres (the point files' CRS after units_scale, before registration, which moves them by centimetres to a metre): only the MLS points inside are ingested, and a COPC input decompresses only its octree nodes over the box, so a city-wide COPC feeds one campus at the cost of its campus part; 'mesh': the meshes' x/y extent grown by one tile and snapped out to the tile grid; None: every point")
    crs: str | None = Field(None, description="projected CRS of the campus, e.g. 'EPSG:32650'; read from the LAS VLRs when absent")
    mesh_offset: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="added to mesh coordinates (ContextCapture SRSOrigin) to get world metres")
    units_scale: float = Field(1.0, description="multiplies input coordinates into metres (e.g. 0.3048 for US feet)")
    labels: str | None = Field(None, description="patch labels: a synth defects.json or a CSV of bad patch ids (i,j,k[,label]); ids are world-anchored, so a CSV stays valid when the campus grows")
    origin: tuple[float, float, float] | None = Field(None, description="campus origin (world metres) of the float32 offsets; default: the inputs' minimum x/y corner snapped to 1 km, z = 0")
    images: str | None = Field(None, description="folder of the vehicle camera images that texture rebuilt regions; default: an 'images' folder beside the first mesh input when it holds a cameras.json")
    cameras: str | None = Field(None, description="camera poses of the images (OpenCV model with radial-tangential distortion), by name: a COLMAP text model (its sparse folder, cameras.txt or images.txt), a ContextCapture/iTwin BlocksExchange .xml, or a cameras.json {'frame': 'MLS' | 'mesh', 'frame_origin': [x, y, z], 'cameras': [{'image', 'K', 'R', 't', 'width', 'height', 'dist'?: [k1, k2, p1, p2, k3]}]}, X_cam = R (X_world - frame_origin) + t. COLMAP and BlocksExchange poses are read as world coordinates in the campus CRS, in the mesh's frame (the photogrammetry that made it); MLS-frame cameras need a cameras.json with 'frame': 'MLS'. Image paths are relative to inputs.images (default: the camera file's folder; for COLMAP also ../images and ../../images); default: images/cameras.json")

    @field_validator("points_bounds")
    @classmethod
    def _box(cls, v):
        if isinstance(v, tuple) and not (v[0] < v[2] and v[1] < v[3]):
            raise ValueError(f"points_bounds is [xmin, ymin, xmax, ymax] with xmin < xmax and ymin < ymax, got {list(v)}")
        return v


class RegistrationConfig(_Model):
    mode: Literal["auto", "pinned", "off"] = Field(
        "auto", description="auto: register when the inputs change; pinned: reuse the recorded transform (or "
        "`matrix`), so a changed input redoes only its tiles; off: inputs are co-registered (a check still warns)")
    matrix: list[list[float]] | None = Field(None, description="a 4x4 similarity MLS -> mesh (campus-local) to use in pinned mode")
    voxel_m: float = Field(0.3, description="voxel size for the coarse stage (downsampling before FPFH)")
    fine_voxel_m: float = Field(0.05, description="voxel size for Scale-ICP")
    max_points: int = Field(400_000, description="cap on MLS points sampled for registration")
    sac_iterations: int = Field(1000, description="SAC-IA iterations (paper: 1000)")
    sac_threshold_m: float = Field(0.10, description="SAC-IA inlier distance (paper: 10 cm)")
    icp_iterations: int = Field(1000, description="Scale-ICP iterations (paper: 1000)")
    icp_threshold_m: float = Field(0.001, description="final Scale-ICP correspondence distance / convergence (paper: 1 mm)")
    with_scale: bool = Field(True, description="estimate a similarity (rotation, translation, scale)")
    target_spacing_m: float = Field(0.15, gt=0, description="spacing of the area-weighted samples of the mesh surface that registration aligns to")
    seed: int = 0
    # the guard (tasks.register.guard): an estimate is applied only when it clearly beats the transform in place
    min_improvement_m: float = Field(0.05, ge=0, description="an estimate replaces the transform in place (identity, or the recorded one) only when it lowers the robust MLS-to-surface distance of held-out points by at least this much ...")
    min_improvement_ratio: float = Field(0.5, ge=0, lt=1, description="... and by at least this share of it (0.5: to half or less); co-registered inputs stay where they are")
    max_scale_error: float = Field(0.001, ge=0, description="scale prior: an estimate whose |scale - 1| exceeds this is refused (1000 ppm; a scanner's scale error is ppm, an MVS mesh's can be ~0.1-0.5 %: raise it for such a mesh; the synth campus states 0.005)")
    max_displacement_m: float = Field(1.0, gt=0, description="displacement prior: an estimate moving any sampled MLS point further than this is flagged (warning, or error when strict)")
    min_fitness: float = Field(0.5, ge=0, le=1, description="an estimate whose final fitness (share of MLS points within the last ICP distance of the mesh) is below this is flagged")
    min_coarse_fitness: float = Field(0.05, ge=0, le=1, description="a coarse (SAC-IA) fitness below this counts as a failed coarse stage and is flagged")
    holdout_share: float = Field(0.2, gt=0, lt=1, description="share of the sampled MLS points held out of the fit to score identity, the recorded transform and the estimate")
    strict: bool = Field(False, description="a flagged registration (failed, low fitness, failed coarse stage, outside the scale or displacement prior) is an error instead of one warning line")

    @model_validator(mode="before")
    @classmethod
    def _enabled_alias(cls, data):
        if isinstance(data, dict) and "enabled" in data:  # the v1 switch: enabled false == mode off
            data = dict(data)
            enabled = data.pop("enabled")
            data.setdefault("mode", "auto" if enabled else "off")
        return data

    @field_validator("mode", mode="before")
    @classmethod
    def _yaml_boolean_mode(cls, v):
        """YAML 1.1 reads an unquoted ``off`` (and ``no``/``false``) as False, ``on``/``yes`` as True."""
        if isinstance(v, bool):
            return "auto" if v else "off"
        return v

    @property
    def enabled(self) -> bool:
        return self.mode != "off"


class TilingConfig(_Model):
    tile_size_m: float = Field(100.0, gt=1.0, description="ground tile edge length")
    chunk_points: int = Field(2_000_000, gt=1000, description="points per ingest chunk (bounds memory)")


class PartitionConfig(_Model):
    patch_size_m: tuple[float, float, float] = Field(
        (2.3, 1.0, 0.7), description="patch cuboid (paper: 23 x 10 x 7, read as metres x 0.1)"
    )
    outlier_sigma_low: float = Field(2.0, ge=0, description="patches with log-count below mean - k*sigma are flagged (paper: histogram + normal fit)")
    outlier_sigma_high: float = Field(3.0, ge=0, description="patches with log-count above mean + k*sigma are flagged")
    min_faces: int = Field(1, ge=0, description="a pair needs at least this many faces to be graded")
    min_points: int = Field(1, ge=0, description="a pair needs at least this many points to be graded")
    memory_budget_mb: int = Field(2048, ge=64, description="peak RSS budget of a tile task (a worker); tiles that would not fit are partitioned by an external merge of sorted runs")
    grid_anchor_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="world point of the patch grid's cell (0, 0, 0); keep it fixed: ids derive from it")

    @field_validator("patch_size_m")
    @classmethod
    def _positive(cls, v):
        if min(v) <= 0:
            raise ValueError("patch sizes must be positive")
        return v


class ClusterConfig(_Model):
    address: str | None = Field(None, description="scheduler address of an existing Dask cluster; None starts a local one")
    n_workers: int = Field(2, ge=1)
    threads_per_worker: int = Field(1, ge=1)
    memory_limit: str = Field("auto")
    prefect_api_url: str | None = Field(None, description="an existing Prefect API; None starts one embedded server")
    tiles_per_task: int = Field(1, ge=1, description="tiles handled by one Prefect task run")


class ReportConfig(_Model):
    enabled: bool = Field(True, description="write output/report.html at the end of every run")
    quality: bool = Field(True, description="measure the model against the truth when the inputs have one (a synth campus); minutes on the demo, cached after")
    quality_spacing_m: float = Field(0.10, gt=0.0, le=0.5, description="spacing of the surface samples the quality against the truth measures (metres); 0.10 gives the figures of 0.05 to 1e-4 on the demo (F@5cm) in half the time")
    max_unknown_share: float = Field(0.5, ge=0.0, le=1.0, description="the run summary warns when more than this share of the patches could not be graded (unknown)")


class QualityConfig(_Model):
    """Accuracy without truth: a share of the MLS held out of the repair and measured against the models."""

    holdout_share: float = Field(0.1, ge=0.0, lt=1.0, description="share of the MLS held out of the repair's fusion and meshing, in whole strips (GPS-time blocks of holdout_block_s seconds of one input file; points without a time: holdout_cell_m ground cells), to measure the input mesh and the merged model on points that shaped neither (report.html, the run summary); 0 turns it off. A patch never loses all its points, so a tile never does (tasks.geometry.holdout)")
    holdout_block_s: float = Field(1.0, gt=0.0, description="length of one held-out strip in GPS seconds (9 m of track at 9 m/s: short enough that a short scan has strips to choose from, the tiny synth campus's scan holds 13); passes driven at different times fall in different strips")
    holdout_cell_m: float = Field(5.0, gt=0.0, description="ground cell (world metres) that stands in for a strip where the points carry no GPS time (gps_time 0)")
    holdout_seed: int = Field(0, description="seed of the strip choice: the same seed, share and points always hold out the same strips")

    def holdout(self) -> Holdout:
        """The strip choice these fields make (:class:`tasks.geometry.holdout.Holdout`)."""
        return Holdout(self.holdout_share, self.holdout_block_s, self.holdout_cell_m, self.holdout_seed)


class CampusConfig(_Model):
    name: str = "campus"
    work_dir: str = "ms3d-work/campus"
    inputs: InputsConfig = Field(default_factory=InputsConfig)
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    tiling: TilingConfig = Field(default_factory=TilingConfig)
    partition: PartitionConfig = Field(default_factory=PartitionConfig)
    cluster: ClusterConfig = Field(default_factory=ClusterConfig)
    report: ReportConfig = Field(default_factory=ReportConfig)
    quality: QualityConfig = Field(default_factory=QualityConfig, description="accuracy without truth: the held-out MLS strips")
    export: ExportConfig = Field(default_factory=lambda: ExportConfig(), description="3D Tiles output (merge has no parameters of its own)")
    classify: ClassifyConfig = Field(default_factory=ClassifyConfig, description="grading of patch pairs (the checkpoint classify.model names: the shipped default is GBM trees)")
    repair: RepairConfig = Field(default_factory=RepairConfig)
    runner: Literal["dask", "local", "inline"] = Field(
        "dask", description="'local': Prefect tasks in the flow process; 'inline': no Prefect at all, one process (debugging, tests)")

    def grid(self) -> PatchGrid:
        """The campus patch grid (patch sizes, tile size, anchor)."""
        return PatchGrid(self.partition.patch_size_m, self.tiling.tile_size_m, self.partition.grid_anchor_m)

    @classmethod
    def from_yaml(cls, path: str | Path, overrides: dict | None = None) -> CampusConfig:
        """Load a YAML config; relative paths are relative to the file. Every problem (missing or
        unreadable file, broken YAML, unknown or invalid field) is an InputError naming the file."""
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise InputError(path, "config file not found") from None
        except IsADirectoryError:
            raise InputError(path, "is a folder, not a YAML config file") from None
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(path, f"cannot read the config ({e})") from None
        try:
            data = yaml.safe_load(text) or {}
        except yaml.YAMLError as e:
            mark = getattr(e, "problem_mark", None)
            where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
            raise InputError(path, f"not valid YAML{where}: {getattr(e, 'problem', None) or e}") from None
        if not isinstance(data, dict):
            raise InputError(path, "the config must be a YAML mapping (name:, inputs:, ...)")
        try:
            return cls._from_dict(data, path, overrides)
        except ValidationError as e:
            raise InputError(path, format_validation_error(e)) from None

    @classmethod
    def _from_dict(cls, data: dict, path: Path, overrides: dict | None) -> CampusConfig:
        base = path.parent
        inputs = data.get("inputs", {})
        for key in ("mesh", "points"):  # relative input paths are relative to the config file
            inputs[key] = [str((base / p) if not (Path(p).is_absolute() or is_url(p)) else p)
                           for p in inputs.get(key, [])]
        for key in ("labels", "images", "cameras"):
            if inputs.get(key) and not (Path(inputs[key]).is_absolute() or is_url(inputs[key])):
                inputs[key] = str(base / inputs[key])
        data["inputs"] = inputs
        if "work_dir" in data and not (Path(data["work_dir"]).is_absolute() or is_url(data["work_dir"])):
            data["work_dir"] = str(base / data["work_dir"])
        for dotted, value in (overrides or {}).items():
            _set_dotted(data, dotted, value)
        return cls.model_validate(data)

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)

    def stage_params(self, stage: str) -> dict:
        """The parameters that decide a stage's output (hashed into the manifest). Paths of inputs are
        not parameters: inputs enter by identity and content fingerprint."""
        reg = self.registration.model_dump(mode="json")
        return {
            "scan": {"mesh_offset": list(self.inputs.mesh_offset), "units_scale": self.inputs.units_scale,
                     "target_spacing_m": self.registration.target_spacing_m},
            "register": {k: v for k, v in reg.items() if k != "target_spacing_m"} | {"crs": self.inputs.crs},
            "ingest": {"grid": self.grid().to_json(), "chunk_points": self.tiling.chunk_points,
                       "mesh_offset": list(self.inputs.mesh_offset), "units_scale": self.inputs.units_scale},
            "partition": {"grid": self.grid().to_json()},
            "labels": {"grid": self.grid().to_json()},
            "outliers": {k: v for k, v in self.partition.model_dump(mode="json").items()
                         if k.startswith(("outlier", "min_"))},
        }.get(stage, {})



def format_validation_error(e: ValidationError) -> str:
    """One line per problem of a pydantic error, with the field path and a hint for unknown keys."""
    parts = []
    for err in e.errors():
        loc = ".".join(str(x) for x in err["loc"])
        if err["type"] == "extra_forbidden":
            parent = CampusConfig
            for key in err["loc"][:-1]:
                ann = parent.model_fields.get(str(key)) if isinstance(key, str) else None
                parent = ann.annotation if ann is not None and isinstance(ann.annotation, type) else None
                if parent is None or not issubclass(parent, BaseModel):
                    break
            known = sorted(parent.model_fields) if parent is not None and isinstance(parent, type) else []
            close = _closest(str(err["loc"][-1]), known)
            hint = f" (did you mean '{close}'?)" if close else (f" (known: {', '.join(known)})" if known else "")
            parts.append(f"unknown field '{loc}'{hint}")
        else:
            parts.append(f"{loc or 'config'}: {err['msg']} (got {err.get('input')!r})")
    return "invalid config: " + "; ".join(parts)


def _closest(word: str, options: list[str]) -> str | None:
    import difflib

    got = difflib.get_close_matches(word, options, n=1, cutoff=0.6)
    return got[0] if got else None


def _set_dotted(d: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    for k in keys[:-1]:
        nxt = d.setdefault(k, {})
        if not isinstance(nxt, dict):
            raise InputError(None, f"--set {dotted}: '{k}' is not a section of the config")
        d = nxt
    d[keys[-1]] = value


class ExportConfig(_Model):
    """3D Tiles export (tasks/export/build.py)."""

    compression: Literal["none", "draco", "meshopt"] = Field("none", description="glb geometry compression: none, Draco (KHR_draco_mesh_compression via DracoPy), or meshopt (EXT_meshopt_compression with KHR_mesh_quantization via glTF-Transform in node; keeps EXT_mesh_features / EXT_structural_metadata)")
    max_texture_px: int = Field(4096, ge=64, le=4096, description="texture atlases are cropped to what a tile uses and downscaled to at most this side length")
    jpeg_quality: int = Field(85, ge=10, le=100, description="quality of re-encoded JPEG textures")
    texture: Literal["jpeg", "ktx2"] = Field("jpeg", description="texture encoding in the glb: jpeg (as cropped and re-encoded), or ktx2 (KTX2 / Basis Universal, KHR_texture_basisu, with mipmaps: UASTC in the leaves, ETC1S in textured parents; through ktx2-encoder in node, slow on CPU: about 30 s (ETC1S) to 90 s (UASTC) per 3k x 3k atlas on one core here); the viewer transcodes it for the GPU")
    before: bool = Field(False, description="also write output/before/: the input mesh as a tileset in the same frame and format, for the viewer's before / after split (about doubles the export's time and size)")
    geoid_grid: str | None = Field(None, description="a PROJ vertical grid file (GeoTIFF or GTX: geoid undulation N by longitude/latitude, e.g. a national geoid) that makes the campus's orthometric heights ellipsoidal when PROJ has no geoid grid of its own for its vertical CRS; None: the EGM96 geoid shipped with ms3d (storage/geoid.py); recorded in georef.json")
    lod_texture_px: int = Field(1024, ge=0, le=4096, multiple_of=4, description="largest side of the atlas each node passes up to its parent (tasks/export/bake.py; sized for about 8 texels per face of the decimated mesh): a parent's content carries its children's atlases packed 2 x 2 (at most twice this side), so texels per metre fall per level as the geometry's detail does; 0: vertex-coloured parents (textures sampled at the vertices), as before")
    lod_reduction: float = Field(4.0, gt=1.0, description="each quadtree level keeps 1/lod_reduction of its children's faces")
    hausdorff_samples: int = Field(20_000, ge=1000, description="points sampled per direction to measure a decimation's deviation")
    decimator: Literal["auto", "fqmr", "pymeshlab"] = Field("auto", description="quadric decimation: pyfqmr (Fast Quadric Mesh Simplification, ~6x faster) or pymeshlab (GPL: the optional gpl extra, pip install 'ms3d[gpl]'); auto = fqmr")
    overview_max_faces: int = Field(300_000, ge=1000, description="faces of output/overview.glb (whole campus, decimated)")
    # tiling layout and packaging (tasks/export/implicit.py, storage/formats/threetz.py)
    tiling: Literal["explicit", "implicit"] = Field("explicit", description="tileset layout: explicit (every tile listed in tileset.json) or implicit (3D Tiles 1.1 implicit QUADTREE tiling: one root tile, content at content/{level}/{x}/{y}.glb, availability in binary subtrees/{level}/{x}/{y}.subtree; each tile's measured box and geometric error kept as TILE_BOUNDING_BOX / TILE_GEOMETRIC_ERROR tile metadata; the same glbs, moved, so switching rebuilds nothing)")
    subtree_levels: int = Field(4, ge=1, le=10, description="levels per implicit subtree file (tiling: implicit): 4 = up to 85 tiles per .subtree; capped at the quadtree's levels")
    archive: Literal["none", "3tz"] = Field("none", description="also pack output/tileset.3tz after the export: a 3D Tiles archive (the 3TZ format: one ZIP with an @3dtilesIndex1@ hash index) of tileset.json, content, subtrees, overview.glb, georef.json, points/ and before/; `ms3d view` serves it; rewritten only when those files change")
    # --- end of tiling layout and packaging ---

    @model_validator(mode="after")
    def _ktx2_without_draco(self):
        if self.texture == "ktx2" and self.compression == "draco":
            raise ValueError("export.texture ktx2 goes with export.compression none or meshopt, not draco")
        return self
