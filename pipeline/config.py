"""Typed, frozen configuration: presets, TOML files and `--set key=value` overrides.

A config is built once (preset -> TOML file -> overrides -> dataset-dependent defaults),
validated, written into the run folder and never mutated afterwards.
"""

from __future__ import annotations

import tomllib
import typing
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Literal

from pipeline.errors import UserError

DatasetFormat = Literal["auto", "replica", "tum"]
GaussianKind = Literal["3d", "2d"]
RenderBackend = Literal["auto", "gsplat", "reference"]
LoaderKind = Literal["pipelined", "sync"]
Switch = Literal["auto", "on", "off"]


@dataclass(frozen=True)
class DatasetConfig:
    path: str = ""  # empty: generate the embedded synthetic scene
    format: DatasetFormat = "auto"
    width: int = 0  # 0: native size; otherwise resize (colour linear, depth nearest)
    height: int = 0
    start: int = 0
    end: int = -1  # exclusive; -1: to the end
    stride: int = 1
    intrinsics: tuple[float, ...] = ()  # (fx, fy, cx, cy) at the stored size; empty: from the layout


@dataclass(frozen=True)
class SyntheticConfig:
    """The embedded default scene; sizes of 0 are chosen by device (small on the CPU)."""

    frames: int = 0
    width: int = 0
    height: int = 0
    seed: int = 0
    speed: float = 0.3  # metres per second along the path
    jitter: float = 0.01  # metres (and radians x 0.5) of hand-held shake
    fps: float = 30.0
    layout: DatasetFormat = "replica"  # replica or tum
    depth_noise: float = 0.0  # TUM layout only: depth noise std = depth_noise x depth^2, metres
    holes: float = 0.0  # TUM layout only: fraction of depth pixels zeroed, in blobs
    time_jitter: float = 0.0  # TUM layout only: depth and pose timestamp offsets up to this, seconds


@dataclass(frozen=True)
class TrackingConfig:
    iters: int = 40
    lr_rotation: float = 0.0  # 0: by dataset (0.0004 Replica-like, 0.002 TUM)
    lr_translation: float = 0.002
    silhouette_threshold: float = 0.99
    lost_translation_m: float = 0.3  # a jump beyond this from the initial guess marks tracking lost
    lost_coverage: float = 0.05  # fewer pixels than this fraction above the threshold marks it lost


@dataclass(frozen=True)
class MappingConfig:
    iters: int = 60
    window: int = 24
    lr_means: float = 1e-4
    lr_colors: float = 2.5e-3
    lr_rotations: float = 1e-3
    lr_opacities: float = 5e-2
    lr_scales: float = 1e-3
    ssim_weight: float = 0.2
    prune_opacity: float = 0.005
    prune_scale_factor: float = 0.1  # x scene radius
    prune_at: tuple[int, ...] = (0, 20)
    scene_radius_divisor: float = 0.0  # 0: by dataset (3 Replica-like, 2 TUM)


@dataclass(frozen=True)
class DensifyConfig:
    silhouette_threshold: float = 0.5
    depth_error_factor: float = 50.0  # x median depth error


@dataclass(frozen=True)
class KeyframeConfig:
    every: int = 5
    overlap_samples: int = 1600


@dataclass(frozen=True)
class LossConfig:
    color_weight: float = 0.5
    depth_weight: float = 1.0


@dataclass(frozen=True)
class GaussianConfig:
    kind: GaussianKind = "3d"
    isotropic: bool = True


@dataclass(frozen=True)
class RenderConfig:
    backend: RenderBackend = "auto"
    packed: bool = False
    eps2d: float = 0.3
    near: float = 0.01
    far: float = 100.0


@dataclass(frozen=True)
class RunConfig:
    output: str = "outputs"
    name: str = ""  # empty: derived from the dataset and preset
    device: str = "auto"  # auto | cpu | cuda
    eval_every: int = 5  # render metrics on every Nth frame
    loader: LoaderKind = "pipelined"
    compile: Switch = "auto"  # torch.compile the per-iteration loss and pose functions (auto: on CUDA)
    queue_size: int = 4
    seed: int = 0


PoseUse = Literal["initial_guess", "groundtruth", "ignore"]


@dataclass(frozen=True)
class LiveConfig:
    """The `serve` daemon and its live sources."""

    width: int = 0  # SLAM's working size; 0: the first frame's (later frames are resized to it)
    height: int = 0
    save_every_s: float = 60.0  # map, trajectory and checkpoint written this often (and at exit)
    status_host: str = "127.0.0.1"
    status_port: int = 8765  # JSON status at http://status_host:status_port/status; 0: off
    retry_initial_s: float = 1.0  # back-off after a failed connection, doubling up to retry_max_s
    retry_max_s: float = 30.0
    connect_timeout_s: float = 10.0  # signalling to first frame
    stall_timeout_s: float = 5.0  # no frame for this long: the phone is gone, reconnect
    device_pose: PoseUse = "initial_guess"  # NeRFCapture: what the phone's pose is used for


@dataclass(frozen=True)
class ViewerConfig:
    enabled: bool = False
    host: str = "127.0.0.1"  # 0.0.0.0 exposes it to the network: deliberately
    port: int = 8080
    max_hz: float = 1.0  # frame snapshots (stats, images, camera) per second at most
    map_every_s: float = 5.0  # the whole map is sent this often at most (~32 bytes per Gaussian; viewer.md)


@dataclass(frozen=True)
class Config:
    preset: str = "base"
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    gaussians: GaussianConfig = field(default_factory=GaussianConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    run: RunConfig = field(default_factory=RunConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    viewer: ViewerConfig = field(default_factory=ViewerConfig)


# tracking iters / mapping iters / mapping window / keyframe every
PRESETS: dict[str, tuple[int, int, int, int]] = {
    "base": (40, 60, 24, 5),
    "small": (10, 15, 15, 5),
    "tiny": (4, 6, 6, 5),
    "tum": (200, 30, 20, 5),
}

# Values that SplaTAM tunes per dataset family.
DATASET_DEFAULTS: dict[str, dict[str, float]] = {
    "replica": {"tracking.lr_rotation": 0.0004, "mapping.scene_radius_divisor": 3.0},
    "tum": {"tracking.lr_rotation": 0.002, "mapping.scene_radius_divisor": 2.0},
}


def preset_config(name: str) -> Config:
    if name not in PRESETS:
        raise UserError(f"unknown preset '{name}' (choose from {', '.join(PRESETS)})")
    track, mapping, window, every = PRESETS[name]
    base = Config(preset=name)
    return replace(
        base,
        tracking=replace(base.tracking, iters=track),
        mapping=replace(base.mapping, iters=mapping, window=window),
        keyframes=replace(base.keyframes, every=every),
    )


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(key: str, raw: Any, hint: Any) -> Any:
    """Convert a TOML value or a `--set` string to the field's declared type."""
    origin = typing.get_origin(hint)
    if origin is Literal:
        choices = typing.get_args(hint)
        if raw not in choices:
            raise UserError(f"bad value for '{key}': {raw!r} (choose from {', '.join(choices)})")
        return raw
    if origin is tuple:
        item = typing.get_args(hint)[0]
        if isinstance(raw, str):
            parts = [p for p in raw.replace(",", " ").split() if p]
        elif isinstance(raw, (list, tuple)):
            parts = list(raw)
        else:
            raise UserError(f"bad value for '{key}': {raw!r} (expected a list)")
        return tuple(_coerce(key, p, item) for p in parts)
    if hint is bool:
        if isinstance(raw, bool):
            return raw
        text = str(raw).strip().lower()
        if text in ("1", "true", "yes", "on"):
            return True
        if text in ("0", "false", "no", "off"):
            return False
        raise UserError(f"bad value for '{key}': {raw!r} (expected true or false)")
    if hint in (int, float):
        if isinstance(raw, bool):
            raise UserError(f"bad value for '{key}': {raw!r} (expected a number)")
        try:
            value = hint(raw)
        except (TypeError, ValueError):
            raise UserError(f"bad value for '{key}': {raw!r} (expected {hint.__name__})") from None
        if hint is int and isinstance(raw, float) and raw != value:
            raise UserError(f"bad value for '{key}': {raw!r} (expected an integer)")
        return value
    if hint is str:
        return str(raw)
    raise UserError(f"cannot set '{key}'")


def with_value(config: Config, key: str, raw: Any) -> Config:
    """A copy of `config` with the dotted `key` (e.g. 'tracking.iters') set to `raw`."""
    *path, last = key.split(".")

    def update(node: Any, depth: int) -> Any:
        names = {f.name for f in fields(node)}
        name = path[depth] if depth < len(path) else last
        if name not in names or name == "preset":
            prefix = ".".join(path[:depth])
            where = f" under '{prefix}'" if prefix else ""
            valid = ", ".join(sorted(n for n in names if n != "preset"))
            raise UserError(f"unknown config key '{key}'{where} (valid: {valid})")
        child = getattr(node, name)
        if depth < len(path):
            if not is_dataclass(child):
                raise UserError(f"unknown config key '{key}'")
            return replace(node, **{name: update(child, depth + 1)})
        if is_dataclass(child):
            raise UserError(f"'{key}' is a section; set one of its keys, e.g. '{key}.{fields(child)[0].name}'")
        return replace(node, **{name: _coerce(key, raw, _hints(type(node))[name])})

    return update(config, 0)


def _flatten(table: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    items: list[tuple[str, Any]] = []
    for name, value in table.items():
        key = f"{prefix}{name}"
        if isinstance(value, dict):
            items.extend(_flatten(value, key + "."))
        else:
            items.append((key, value))
    return items


def parse_overrides(pairs: list[str]) -> list[tuple[str, str]]:
    parsed = []
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise UserError(f"bad --set '{pair}': expected key=value, e.g. tracking.iters=20")
        parsed.append((key.strip(), value.strip()))
    return parsed


def load_config(
    preset: str = "base", config_file: str | Path | None = None, overrides: list[str] | None = None
) -> Config:
    """Preset, then the TOML file's keys, then `--set` overrides (last wins)."""
    items: list[tuple[str, Any]] = []
    if config_file is not None:
        path = Path(config_file)
        try:
            table = tomllib.loads(path.read_text())
        except FileNotFoundError:
            raise UserError(f"config file not found: {path}") from None
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise UserError(f"cannot read config file {path}: {exc}") from None
        preset = str(table.pop("preset", preset))
        items.extend(_flatten(table))
    items.extend(parse_overrides(overrides or []))
    config = preset_config(preset)
    for key, value in items:
        config = with_value(config, key, value)
    validate(config)
    return config


def with_dataset_defaults(config: Config, dataset_format: str) -> Config:
    """Fill the per-dataset values left at 0 (see DATASET_DEFAULTS)."""
    for key, value in DATASET_DEFAULTS[dataset_format].items():
        section, name = key.split(".")
        if getattr(getattr(config, section), name) == 0:
            config = with_value(config, key, value)
    return config


def validate(config: Config) -> None:
    checks = [
        (config.tracking.iters >= 0, "tracking.iters must be >= 0"),
        (config.mapping.iters >= 0, "mapping.iters must be >= 0"),
        (config.mapping.window >= 2, "mapping.window must be >= 2"),
        (config.keyframes.every >= 1, "keyframes.every must be >= 1"),
        (config.keyframes.overlap_samples >= 1, "keyframes.overlap_samples must be >= 1"),
        (config.dataset.stride >= 1, "dataset.stride must be >= 1"),
        (config.dataset.start >= 0, "dataset.start must be >= 0"),
        (len(config.dataset.intrinsics) in (0, 4), "dataset.intrinsics takes fx,fy,cx,cy"),
        ((config.dataset.width > 0) == (config.dataset.height > 0), "set both dataset.width and dataset.height"),
        (config.run.eval_every >= 1, "run.eval_every must be >= 1"),
        (config.run.queue_size >= 1, "run.queue_size must be >= 1"),
        (config.run.device in ("auto", "cpu", "cuda"), "run.device must be auto, cpu or cuda"),
        (0.0 <= config.render.eps2d, "render.eps2d must be >= 0"),
        (0.0 < config.render.near < config.render.far, "need 0 < render.near < render.far"),
        ((config.live.width > 0) == (config.live.height > 0), "set both live.width and live.height"),
        (config.live.save_every_s > 0, "live.save_every_s must be > 0"),
        (config.viewer.max_hz > 0 and config.viewer.map_every_s >= 0, "viewer rates must be positive"),
        (0 < config.live.retry_initial_s <= config.live.retry_max_s, "need 0 < live.retry_initial_s <= retry_max_s"),
        (config.live.connect_timeout_s > 0 and config.live.stall_timeout_s > 0, "live timeouts must be > 0"),
    ]
    for ok, message in checks:
        if not ok:
            raise UserError(message)


def to_toml(config: Config) -> str:
    """The config as a TOML file that `--config` reads back to an equal config."""
    lines = [f'preset = "{config.preset}"']
    for section in fields(config):
        value = getattr(config, section.name)
        if not is_dataclass(value):
            continue
        lines.append(f"\n[{section.name}]")
        for item in fields(value):
            lines.append(f"{item.name} = {_toml_value(getattr(value, item.name))}")
    return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)
