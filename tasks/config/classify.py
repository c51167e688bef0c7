"""Configuration of the classify stage (the ``classify:`` section of a campus config)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class ClassifyConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", protected_namespaces=())

    enabled: bool = Field(True, description="grade every (mesh patch, point patch) pair with the network")
    model: str | None = Field(None, description="checkpoint (.pt) to grade with; None: the shipped default "
                              "model (ms3d_model/weights/default.pt)")
    threshold: float = Field(0.5, ge=0.0, le=1.0, description="a pair is bad (grade 1) when its score (probability of bad) reaches this")
    batch_size: int = Field(64, ge=1, description="pairs per forward pass (inference)")
    threads: int = Field(1, ge=1, description="torch threads per worker process (a Dask worker runs one tile at a time)")
