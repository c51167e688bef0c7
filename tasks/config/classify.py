"""Configuration of the classify stage (the ``classify:`` section of a campus config)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class ClassifyConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", protected_namespaces=())

    enabled: bool = Field(True, description="grade every (mesh patch, point patch) pair with the network")
    model: str | None = Field(None, description="checkpoint (.pt) to grade with; None: the shipped default "
                              "model (ms3d_model/weights/default.pt)")
    threshold: float | None = Field(None, ge=0.0, le=1.0, description="a pair is bad (grade 1) when its score (probability "
                                    "of bad) reaches this; None: the threshold the checkpoint ships (chosen on "
                                    "validation; 0.5 for checkpoints without one)")
    user_labels: bool = Field(True, description="the user's labels (WORKDIR/labels/*.csv, from `ms3d view --label`) "
                              "set the grade of the patches they name, over the model and the evidence")
    outliers: Literal["grade", "unknown"] = Field(
        "grade", description="patches the outliers stage flags by their point or face count (the paper's §3.2.2 "
        "normal fit; tiles/*/outliers.parquet): 'grade' grades them like any pair; 'unknown' leaves them "
        "ungraded (grade -1, the reason in grades.parquet's metadata and the unit record), as the paper leaves them "
        "out of its data. Measured on synth demo campuses 7, 11, 13: count outliers are 4.8-5.5 % of the "
        "labelled patches and hold 5.2-7.6 % of the bad ones (bad rate 0.24-0.29 against 0.21-0.22 elsewhere: "
        "a hole's rim is a patch with few faces), so 'unknown' costs repair that recall")
    batch_size: int = Field(64, ge=1, description="pairs per forward pass (inference)")
    threads: int = Field(1, ge=1, description="torch threads per worker process (a Dask worker runs one tile at a time)")
    # geometric evidence beside the network (tasks.classify.evidence): bad when the model says bad OR the
    # MLS points lie off the mesh. Tuned on synth tiny seeds 7, 11, 23 (coarse block model and MVS); see
    # benchmarks/coarse_bench.py for the measured recall / precision
    evidence: bool = Field(True, description="also grade a patch bad when its MLS points lie off the mesh surface "
                           "(a recess, balcony or passage the mesh lacks), and a points-only patch next to the mesh "
                           "likewise (else it stays unknown); the network's score is kept")
    evidence_off_surface_m: float = Field(0.22, gt=0, description="points off the surface: the evidence_quantile of "
                                          "their distances to the faces of the patch and its 26-neighbours exceeds this "
                                          "(LoD2 tolerance 0.2 m + scanner noise; per-patch 0.95 quantiles of good "
                                          "pairs: p99 0.04-0.07 m on block models, 0.14-0.20 m on MVS meshes)")
    evidence_quantile: float = Field(0.95, gt=0, le=1, description="robust upper quantile of a patch's point-to-surface distances")
    evidence_min_points: int = Field(5, ge=1, description="points a patch needs for evidence (those that count)")
    evidence_min_off_points: int = Field(3, ge=1, description="points beyond evidence_off_surface_m a patch needs to be bad")
    evidence_near_m: float = Field(1.5, gt=0, description="a points-only patch is bad only when its points lie within this "
                                   "of the mesh (against the modelled surface; open ground, trees far off stay unknown)")
    evidence_standing_normal_z: float = Field(0.7, ge=0, le=1, description="a point off the surface whose nearest face is "
                                              "this flat (|n_z| above) stands on ground or roof (car, person, bush) and "
                                              "does not count")
