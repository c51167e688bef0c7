"""Typed run configuration (pydantic): the campus config and its stage sections.

``tasks.config.campus`` holds the campus-level models and :class:`CampusConfig`; the classify and repair
sections live beside it. Callers import from here.
"""

from tasks.config.campus import (
    CampusConfig,
    ClusterConfig,
    ExportConfig,
    InputsConfig,
    PartitionConfig,
    QualityConfig,
    RegistrationConfig,
    ReportConfig,
    TilingConfig,
)
from tasks.config.classify import ClassifyConfig
from tasks.config.repair import (
    FusionConfig,
    MeshConfig,
    RegionsConfig,
    RepairConfig,
    TextureConfig,
    TypedRepairConfig,
)

__all__ = ["CampusConfig", "ClassifyConfig", "ClusterConfig", "ExportConfig", "FusionConfig", "InputsConfig",
           "MeshConfig", "PartitionConfig", "QualityConfig", "RegionsConfig", "RegistrationConfig", "RepairConfig", "ReportConfig",
           "TextureConfig", "TilingConfig", "TypedRepairConfig"]
