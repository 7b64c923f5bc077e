"""Typed, frozen configuration: the schema (`schema.py`) and how a config is built (`loading.py`)."""

from pipeline.config.loading import (
    load_config,
    parse_overrides,
    preset_config,
    to_toml,
    validate,
    with_dataset_defaults,
    with_value,
)
from pipeline.config.schema import (
    DATASET_DEFAULTS,
    PRESETS,
    SYNTHETIC_CPU,
    SYNTHETIC_GPU,
    Config,
    DatasetConfig,
    DatasetFormat,
    DensifyConfig,
    GaussianConfig,
    GaussianKind,
    KeyframeConfig,
    LiveConfig,
    LoaderKind,
    LossConfig,
    MappingConfig,
    PoseUse,
    RenderBackend,
    RenderConfig,
    RunConfig,
    Switch,
    SyntheticConfig,
    TrackingConfig,
    ViewerConfig,
    ViewerKind,
)

__all__ = [
    "DATASET_DEFAULTS", "PRESETS", "SYNTHETIC_CPU", "SYNTHETIC_GPU", "Config", "DatasetConfig", "DatasetFormat", "DensifyConfig", "GaussianConfig",
    "GaussianKind", "KeyframeConfig", "LiveConfig", "LoaderKind", "LossConfig", "MappingConfig", "PoseUse",
    "RenderBackend", "RenderConfig", "RunConfig", "Switch", "SyntheticConfig", "TrackingConfig", "ViewerConfig",
    "ViewerKind",
    "load_config", "parse_overrides", "preset_config", "to_toml", "validate", "with_dataset_defaults", "with_value",
]  # fmt: skip
