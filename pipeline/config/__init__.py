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
    PRESET_TRACKING,
    PRESETS,
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
    MapOptimizerKind,
    MappingConfig,
    PoseUse,
    RenderBackend,
    RenderConfig,
    RunConfig,
    Schedule,
    SlamConfig,
    Switch,
    SyntheticConfig,
    TrackingConfig,
    TrackingMethod,
    ViewerConfig,
)

__all__ = [
    "DATASET_DEFAULTS", "PRESET_TRACKING", "PRESETS", "Config", "DatasetConfig", "DatasetFormat", "DensifyConfig",
    "GaussianConfig", "GaussianKind", "KeyframeConfig", "LiveConfig", "LoaderKind", "LossConfig", "MapOptimizerKind",
    "MappingConfig", "PoseUse", "RenderBackend", "RenderConfig", "RunConfig", "Schedule", "SlamConfig", "Switch",
    "SyntheticConfig", "TrackingConfig", "TrackingMethod", "ViewerConfig",
    "load_config", "parse_overrides", "preset_config", "to_toml", "validate", "with_dataset_defaults", "with_value",
]  # fmt: skip
