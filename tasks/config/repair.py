"""Typed configuration of the repair stages (regions -> fuse -> mesh -> texture), ``CampusConfig.repair``.

Pure pydantic, no heavy imports: ``tasks.config.campus`` imports it. Every threshold notes where its default
comes from (the paper names none of them: §5 gives the method, not the values; ours are measured on
synth campuses, see ``benchmarks/quality_bench.py`` and ``docs/benchmarks.md``).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class RegionsConfig(_Section):
    """Connected bad patches -> regions (``tasks.regions.plan``)."""

    min_patches: int = Field(1, ge=1, description="regions with fewer bad patches are left to the mesh")
    grow_cells: int = Field(0, ge=0, le=3, description="growth margin: the bad set is dilated by this many cells "
                            "(26-neighbourhood) before the components are taken; grown cells are rebuilt too")
    context_cells: int = Field(2, ge=1, le=4, description="ring of neighbouring cells read (not rebuilt): the "
                               "retained faces the rebuilt mesh welds to, and MLS context for normals")
    memory_budget_mb: float = Field(1024.0, gt=0, description="a region whose estimated working set exceeds "
                                    "this is split along its longest axis (the halves weld to each other's "
                                    "original border vertices)")


class FusionConfig(_Section):
    """Graph-cut fusion of mesh vertices (reference) and MLS points (candidates), §5.1 (``tasks.repair.fuse``)."""

    sigma_distance_m: float = Field(0.06, gt=0, description="similarity exp(-d²/2σd² - θ²/2σθ²): distance scale "
                                    "(0.04, 0.06, 0.1 measure the same with the typed repair on: its cut dominates)")
    sigma_angle_deg: float = Field(25.0, gt=0, description="similarity: normal-angle scale")
    similarity_threshold: float = Field(0.25, gt=0, lt=1, description="a mesh vertex whose best MLS similarity "
                                        "exceeds this prefers to be replaced (the paper's 'threshold')")
    search_radius_m: float = Field(0.25, gt=0, description="MLS points farther than this never match a vertex")
    point_reach_m: float = Field(0.6, gt=0, description="MLS points farther than this in front of the mesh "
                                 "(scanner side) are clutter (fences, cars, trees) and rejected")
    point_depth_m: float = Field(1.2, gt=0, description="MLS points may lie this far behind the mesh (a "
                                 "protrusion hides the wall behind it)")
    k_neighbours: int = Field(8, ge=2, le=32, description="k of the k-NN smoothness graph")
    smoothness: float = Field(0.6, ge=0, description="weight of the smoothness term (per k-NN edge)")
    unary_weight: float = Field(4.0, gt=0, description="weight of the data terms")
    normal_k: int = Field(12, ge=5, le=64, description="neighbours of the PCA normal estimate (MLS points)")
    mls_spacing_m: float = Field(0.05, gt=0, description="MLS points are thinned to one per voxel of this size "
                                 "before fusion (real MLS density is far above what the mesh needs); 5 cm scores above 3 cm "
                                 "and like 7 cm on the development campus (docs/benchmarks.md)")
    thin: bool = Field(True, description="false: every MLS point of a region is fused, not one per mls_spacing_m "
                       "voxel; the evidence tolerances still follow mls_spacing_m, so this measures what the thinning "
                       "alone costs (at real density: several times the time and memory of a region)")
    detail_spacing_m: float = Field(0.025, ge=0, description="where the 5 cm-thinned MLS surface is not flat (its "
                                    "neighbours within detail_radius_m do not fit a plane to detail_tolerance_m "
                                    "RMS: a window's frame and reveal, a balcony's edge) the points are thinned to one "
                                    "per voxel of this size instead of mls_spacing_m; 0 or >= mls_spacing_m: off. It keeps "
                                    "the small parts (glass, frames, balconies) that 5 cm voxels lose against unthinned "
                                    "fusion (docs/benchmarks.md)")
    detail_tolerance_m: float = Field(0.02, gt=0, description="RMS distance to the neighbourhood's plane (radius "
                                      "detail_radius_m) above which a stretch gets detail_spacing_m")
    detail_radius_m: float = Field(0.15, gt=0, description="radius of the neighbourhood the plane of "
                                   "detail_tolerance_m is fitted to (a relief marks a band this wide on each side)")
    drop_classes: tuple[int, ...] = Field((3, 4, 5, 7, 18), description="ASPRS classes never fused "
                                          "(vegetation, noise)")


class TypedRepairConfig(_Section):
    """Evidence of the defect type per region and repair by type (beyond the paper's single repair)."""

    enabled: bool = Field(True, description="repair by type; false: the paper's single repair everywhere")
    offset_m: float = Field(0.06, gt=0, description="a mesh vertex this far in front of / behind the MLS surface "
                            "is evidence of a protrusion / recess")
    conflict_radius_m: float = Field(0.5, ge=0, description="a mesh vertex with an accepted MLS point this close but no "
                                     "similar one contradicts the scan and is cut (such vertices are rarely within 5 cm "
                                     "of the truth; 0.3 m scores lower, 0.8 m the same: docs/benchmarks.md); 0 disables")
    conflict_cone_deg: float = Field(45.0, gt=0, le=90, description="the contradicting MLS point must lie within "
                                     "this angle of the vertex normal line (in front or behind): a scanned wall top "
                                     "beside a roof edge the scanner never saw does not cut the roof; 90: any point "
                                     "within conflict_radius_m")
    conflict_min_cos: float = Field(0.7, ge=0, le=1, description="... and face like the vertex (|cos| of the normals "
                                    "at least this): a parallel surface displaced contradicts a vertex, a wall meeting "
                                    "the roof at its edge does not; 0: any orientation")
    front_m: float = Field(0.0, ge=0, description="a mesh vertex farther than conflict_radius_m from the MLS but this far "
                           "in front of the nearest scanned surface (on the scanner's side of it) stands where the "
                           "laser passed: cut it (melted eaves hanging off a scanned wall); 0 disables (the default: "
                           "at 0.15 and 0.3 m its gains and losses cancel on the development campus)")
    front_reach_m: float = Field(3.0, gt=0, description="scanned surface farther than this from a vertex says nothing of it")
    uncovered: Literal["keep", "fill"] = Field("fill", description="a region the MLS does not cover is left to "
                                                "the mesh: 'fill' re-triangulates its own vertices in its chart, "
                                                "closing its holes from the mesh alone (never worse than 'keep' on "
                                                "the development campus); 'keep' leaves its faces")
    min_coverage: float = Field(0.15, ge=0, le=1, description="regions whose surface the MLS covers less than this "
                                "are left to the mesh (a hole no scanner saw)")


class MeshConfig(_Section):
    """Triangulation of the fused points, clipping and stitching, §5.2 (``tasks.repair.mesh``)."""

    method: Literal["delaunay", "poisson"] = Field("delaunay", description="delaunay: the fused points "
                                                   "triangulated in the region's chart (Gopi et al. 2000 style, "
                                                   "interpolating); poisson: screened Poisson of the fused points, "
                                                   "density-trimmed, triangulated in the same chart. delaunay is the "
                                                   "default: more accurate at about half the time (docs/benchmarks.md)")
    poisson_depth: int = Field(9, ge=5, le=12, description="octree depth of screened Poisson per region")
    poisson_trim_quantile: float = Field(0.05, ge=0, lt=0.5, description="Poisson vertices of lower density "
                                         "than this quantile are trimmed")
    max_map_distance_m: float = Field(1.2, gt=0, description="fused points farther than this from the region's "
                                      "chart surface are not triangulated")
    flat_spacing_m: float = Field(0.15, ge=0, description="fused MLS points on a flat stretch (neighbours within "
                                  "this radius fit a plane to flat_tolerance_m RMS, the point not at the scan's edge) "
                                  "are thinned to one per voxel of this size before the triangulation "
                                  "(tasks.repair.coarsen): at real MLS density a flat wall would otherwise carry several "
                                  "rebuilt faces per input face; 0: every fused point is triangulated")
    flat_tolerance_m: float = Field(0.015, gt=0, description="RMS distance to the neighbourhood's plane under which "
                                    "a stretch counts as flat (flat_spacing_m). 1.5 cm: above a wall's scan noise "
                                    "(4-10 mm), below what a 5 cm relief over a third of the neighbourhood gives "
                                    "(2.3 cm), so every relief the F@5cm score can see keeps its points")
    max_edge_m: float = Field(0.6, gt=0, description="rebuilt triangles with a longer 3D edge (a fold of the "
                              "chart) are dropped")
    fill_step_m: float = Field(0.4, ge=0, description="where no fused point (kept vertex or accepted MLS point) "
                               "and no replaced vertex lies within this distance, the zone's own surface is sampled "
                               "at this spacing and triangulated with the fused points: a surface the MLS did not "
                               "see keeps the input mesh (tasks.repair.fill); 0: fused points only (the paper)")
    fill_clears_replaced: bool = Field(True, description="no input-surface sample within fill_step_m of a vertex the "
                                       "fusion replaced (a protrusion cut back is not put back); false: only the fused "
                                       "points' feet clear the input surface")
    keep_unseen_m: float = Field(0.5, ge=0, description="zone faces with no MLS point within this distance and no "
                                 "vertex the MLS surface covers (a roof strip the street scanner never saw) stay as "
                                 "they are and the rebuild stitches to them (tasks.repair.keep); 0: every zone face "
                                 "is rebuilt (the paper)")
    overhead_min_height_m: float = Field(2.5, ge=0, description="zone faces within 45° of horizontal whose lowest "
                                         "vertex lies this far or more above the region's lowest MLS point (1st "
                                         "percentile) are overhead: a street scanner saw them from below only, so an "
                                         "MLS point more than 5 cm under such a face (an eave's soffit under the roof's "
                                         "top) is not evidence of it, and keep_unseen_m keeps it (tasks.repair.keep); "
                                         "0: every point counts")
    keep_min_area_m2: float = Field(1.0, ge=0, description="kept (unseen) pieces of the zone smaller than this are "
                                    "rebuilt, then pieces to rebuild this small are kept (unless the whole rebuild is one "
                                    "such piece without an overhead face), so the zone is not cut into specks "
                                    "(tasks.repair.keep.tidy_keep); 0: as found")
    keep_agreeing_m: float = Field(0.05, ge=0, description="MLS points farther than this from every face of a "
                                   "region (in clusters: 3 within 3 x fusion.mls_spacing_m) are surface the mesh does "
                                   "not explain; zone faces farther than agree_band_m from all of them stay as they "
                                   "are, the rest is rebuilt (tasks.repair.agree): open edges, slivers, seams and hidden "
                                   "layers the scan agrees with are never rebuilt; 0: the whole zone is rebuilt")
    agree_band_m: float = Field(0.5, ge=0, description="zone faces within this distance of surface the mesh does not "
                                "explain are rebuilt (keep_agreeing_m): the ring the rebuild stitches into")
    retained_point_m: float = Field(0.1, ge=0, description="an MLS point of the zone within this distance of a "
                                    "retained (context or kept) face, straight along its normal, and farther by this "
                                    "from every face to rebuild is explained by the retained face and not fused into the "
                                    "rebuild (tasks.repair.keep.on_retained): the MLS seeing a kept roof's top over an "
                                    "eave otherwise folds the soffit's chart up to it; 0: every zone point is fused")
    stand_off_m: float = Field(0.05, ge=0, description="fused MLS points more than this above an up-facing stretch "
                               "of their chart (unit normal z >= 0.8) whose own normal is more than 60° from the "
                               "chart's (the legs of a person, a bollard: things standing on the ground) are not "
                               "triangulated into it (tasks.repair.standing); 0: every point in reach is")
    free_surface: bool = Field(True, description="MLS points of a region farther than max_map_distance_m from every "
                               "face (a passage through a block model, a wall the mesh lost) are meshed on their own "
                               "(Poisson, cut back to the points: tasks.repair.free) and added, not welded")
    free_min_points: int = Field(50, ge=3, description="fewer such points (after thinning) are left alone")
    free_off_surface_m: float = Field(0.25, gt=0, description="a point this close to a retained face is explained "
                                      "by it and not meshed freely (a passage wall's foot next to the ground)")
    max_unsupported_share: float = Field(0.3, ge=0, le=1, description="a region whose rebuilt surface lies more than "
                                         "this area share off both the MLS points and the input surface "
                                         "(tasks.repair.support) falls back to the input mesh; 1: never")
    drop_unsupported_m: float = Field(0.05, ge=0, description="rebuilt faces with most of their samples farther "
                                      "than this from both the MLS surface (the tangent plane of an MLS point within "
                                      "drop_unsupported_reach_m) and the input zone surface are dropped: chords of the "
                                      "chart triangulation across a scan gap, a corner or a recess (tasks.repair."
                                      "support.unsupported_faces); the surface is left open there; 0: kept")
    drop_unsupported_reach_m: float = Field(0.3, gt=0, description="an MLS point farther than this from a sample "
                                            "of a rebuilt face does not support it (drop_unsupported_m)")
    restore_dropped_m: float = Field(1.0, ge=0, description="zone faces that only a dropped rebuilt face covered "
                                     "(within this depth along their normal) and that no unexplained scan point "
                                     "contradicts are kept as they were (tasks.repair.restore); 0: left open")
    restore_scope: Literal["dropped", "uncovered", "any"] = Field(
        "uncovered", description="which replaced zone faces restore_dropped_m may keep: 'dropped', those a dropped "
        "chord covered; 'uncovered', every one the final rebuild does not cover (a chord dropped, or never built "
        "there), that continues the retained input and that no unexplained scan point contradicts; 'any', the "
        "same without the last condition (where the scan shows the input wrong but gave nothing to replace it). "
        "Applied with the dropping of unsupported faces: with drop_unsupported_m 0 nothing is restored")
    stitch_tolerance_m: float = Field(0.01, gt=0, description="largest border gap accepted between the rebuilt "
                                      "mesh and the retained mesh")
    max_hole_loop_m: float = Field(40.0, gt=0, description="open boundary loops of the mesh shorter than this "
                                   "inside a region are holes, filled in the chart; longer ones are the mesh edge")


class TextureConfig(_Section):
    """Projective texture mapping from the vehicle images, §5.3 (``tasks.repair.texture``)."""

    enabled: bool = Field(True, description="false: rebuilt faces take the original mesh colours only")
    px_per_m: float = Field(120.0, gt=0, description="atlas resolution target; charts are resampled to this")
    max_atlas_px: int = Field(4096, ge=256, le=8192)
    max_view_angle_deg: float = Field(75.0, gt=0, lt=90, description="views more oblique than this are never used")
    max_distance_m: float = Field(40.0, gt=0)
    seam_weight: float = Field(0.5, ge=0, description="Potts weight of a seam between adjacent faces (in units "
                           "of the per-face view cost)")
    occluder_voxel_m: float = Field(0.2, gt=0, description="MLS points off the mesh are voxelised at this size "
                                    "into occluders (trees, cars) for the visibility test")
    occluder_radius_m: float = Field(25.0, gt=0, description="MLS occluders are gathered this far around a region")
    images: str | None = Field(None, description="folder of the vehicle camera images; default: an 'images' folder "
                               "beside the first mesh input (synth layout)")
    cameras: str | None = Field(None, description="cameras.json (OpenCV pinhole: K, R, t per image, 'frame': MLS "
                                "or mesh); default: images/cameras.json")


class RepairConfig(_Section):
    """The repair of bad regions: which grades, how regions form, fuse, mesh, texture."""

    enabled: bool = True
    grades: Literal["auto", "model", "labels", "all"] = Field(
        "auto", description="auto: the classify stage's grades.parquet when present, else labels.parquet; "
        "model / labels: only that one (a tile without it has no bad patches); all: rebuild every patch from "
        "the fused points (better geometry at several times the repair time and about twice the peak memory "
        "per region: docs/benchmarks.md)")
    regions: RegionsConfig = Field(default_factory=RegionsConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    typed: TypedRepairConfig = Field(default_factory=TypedRepairConfig)
    mesh: MeshConfig = Field(default_factory=MeshConfig)
    texture: TextureConfig = Field(default_factory=TextureConfig)

    def params(self) -> dict:
        """What decides a region's output (hashed into its manifest record); image paths enter by content."""
        d = self.model_dump(mode="json")
        d["texture"] = {k: v for k, v in d["texture"].items() if k not in ("images", "cameras")}
        return d
