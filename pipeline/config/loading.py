"""Building a config: preset -> TOML file -> `--set key=value` overrides -> dataset defaults.

A config is built once, validated, written into the run folder and never mutated afterwards.
"""

from __future__ import annotations

import math
import tomllib
import typing
from dataclasses import fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Literal

import tomli_w

from pipeline.config.schema import DATASET_DEFAULTS, PRESET_TRACKING, PRESETS, Config
from pipeline.errors import UserError


def preset_config(name: str) -> Config:
    if name not in PRESETS:
        raise UserError(f"unknown preset '{name}' (choose from {', '.join(PRESETS)})")
    track, mapping, window, every = PRESETS[name]
    base = Config(preset=name)
    return replace(
        base,
        tracking=replace(base.tracking, iters=track, method=PRESET_TRACKING[name]),
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
        if not math.isfinite(value):
            raise UserError(f"bad value for '{key}': {raw!r} (expected a finite number)")
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


def _port(port: int, off: bool = False) -> bool:
    return (off and port == 0) or 1 <= port <= 65535


def _negative_learning_rate(config: Config) -> str | None:
    """The key of the first negative learning rate, if any (NaN is refused when read)."""
    for name, section in (("tracking", config.tracking), ("mapping", config.mapping)):
        for item in fields(section):
            if item.name.startswith("lr_") and getattr(section, item.name) < 0:
                return f"{name}.{item.name}"
    return None


def validate(config: Config) -> None:
    negative_rate = _negative_learning_rate(config)
    dataset, live, synthetic = config.dataset, config.live, config.synthetic
    checks = [
        (negative_rate is None, f"{negative_rate} must be >= 0 (a learning rate)"),
        (config.loss.color_weight >= 0 and config.loss.depth_weight >= 0, "loss weights must be >= 0"),
        (all(v > 0 for v in dataset.intrinsics), "dataset.intrinsics fx,fy,cx,cy must be positive"),
        (dataset.width >= 0 and dataset.height >= 0, "dataset.width and dataset.height must be >= 0 (0: native)"),
        (live.width >= 0 and live.height >= 0, "live.width and live.height must be >= 0 (0: the first frame's)"),
        (min(synthetic.frames, synthetic.width, synthetic.height) >= 0, "synthetic sizes must be >= 0 (0: by device)"),
        (_port(live.status_port, off=True), "live.status_port must be a port, 1 to 65535 (0: no status endpoint)"),
        (_port(config.viewer.port), "viewer.port must be a port, 1 to 65535"),
        (config.run.save_every_s > 0, "run.save_every_s must be > 0"),
        (config.tracking.iters >= 0, "tracking.iters must be >= 0"),
        (config.tracking.refine_iters >= 0, "tracking.refine_iters must be >= 0"),
        (
            1 <= len(config.tracking.align_iters) <= 6 and min(config.tracking.align_iters, default=0) >= 1,
            "tracking.align_iters takes 1 to 6 iteration counts (one per pyramid level, coarse to fine), each >= 1",
        ),
        (
            min(config.tracking.align_depth_sigma_m, config.tracking.align_color_sigma) > 0,
            "tracking.align_depth_sigma_m and align_color_sigma must be > 0",
        ),
        (config.tracking.align_photometric_weight >= 0, "tracking.align_photometric_weight must be >= 0"),
        (0 <= config.tracking.align_min_silhouette < 1, "tracking.align_min_silhouette must be in [0, 1)"),
        (config.tracking.align_max_depth_diff_m > 0, "tracking.align_max_depth_diff_m must be > 0"),
        (0 <= config.tracking.align_min_inliers <= 1, "tracking.align_min_inliers must be in [0, 1]"),
        (0 <= config.tracking.align_min_conditioning < 1, "tracking.align_min_conditioning must be in [0, 1)"),
        (
            min(config.tracking.align_max_residual_m, config.tracking.align_max_intensity_rms) > 0,
            "tracking.align_max_residual_m and align_max_intensity_rms must be > 0",
        ),
        (config.tracking.align_recovery_iters >= 0, "tracking.align_recovery_iters must be >= 0"),
        (config.tracking.relocalise_candidates >= 0, "tracking.relocalise_candidates must be >= 0"),
        (config.mapping.iters >= 0, "mapping.iters must be >= 0"),
        (config.mapping.window >= 2, "mapping.window must be >= 2"),
        (config.slam.max_lead >= 0, "slam.max_lead must be >= 0"),
        (config.mapping.views_per_step >= 1, "mapping.views_per_step must be >= 1"),
        (config.keyframes.max_kept == 0 or config.keyframes.max_kept >= 2, "keyframes.max_kept must be 0 or >= 2"),
        (config.mapping.max_gaussians >= 0, "mapping.max_gaussians must be >= 0"),
        (config.live.max_keyframes >= 2 and config.live.max_gaussians >= 1, "live bounds must be positive"),
        (config.keyframes.every >= 1, "keyframes.every must be >= 1"),
        (config.keyframes.overlap_samples >= 1, "keyframes.overlap_samples must be >= 1"),
        (0 <= config.keyframes.min_overlap <= 1, "keyframes.min_overlap must be in [0, 1]"),
        (config.keyframes.max_translation > 0, "keyframes.max_translation must be > 0"),
        (0 <= config.keyframes.min_coverage <= 1, "keyframes.min_coverage must be in [0, 1]"),
        (synthetic.loops >= 0, "synthetic.loops must be >= 0"),
        (config.loops.min_keyframes_back >= 2, "loops.min_keyframes_back must be >= 2"),
        (config.loops.max_candidates >= 1, "loops.max_candidates must be >= 1"),
        (
            1 <= len(config.loops.verify_iters) <= 6 and min(config.loops.verify_iters, default=0) >= 1,
            "loops.verify_iters takes 1 to 6 iteration counts (one per pyramid level, coarse to fine), each >= 1",
        ),
        (
            min(config.loops.information_scale, config.loops.odometry_sigma_m, config.loops.odometry_sigma_deg) > 0,
            "loops.information_scale, odometry_sigma_m and odometry_sigma_deg must be > 0",
        ),
        (
            min(config.loops.max_loop_residual_m, config.loops.max_loop_residual_deg, config.loops.loop_kernel_width)
            > 0,
            "loops.max_loop_residual_m, max_loop_residual_deg and loop_kernel_width must be > 0",
        ),
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
        (config.live.busy_probe_s > 0, "live.busy_probe_s must be > 0"),
        (
            min(config.live.connect_timeout_s, config.live.stall_timeout_s, config.live.http_timeout_s) > 0,
            "live timeouts must be > 0",
        ),
        (0 <= config.live.dds_domain <= 232, "live.dds_domain must be a DDS domain id, 0 to 232"),
    ]
    for ok, message in checks:
        if not ok:
            raise UserError(message)


def to_toml(config: Config) -> str:
    """The config as a TOML file that `--config` reads back to an equal config (written by
    tomli-w, which escapes every string TOML needs escaped: control characters, newlines)."""
    table: dict[str, Any] = {"preset": config.preset}
    for section in fields(config):
        value = getattr(config, section.name)
        if is_dataclass(value):
            table[section.name] = {item.name: getattr(value, item.name) for item in fields(value)}
    return tomli_w.dumps(table)


def toml_value(value: Any) -> str:
    """One value as TOML writes it, on one line (`gsplatam config` shows defaults so)."""
    if isinstance(value, tuple):  # tomli-w puts an array's items a line each
        return "[" + ", ".join(toml_value(item) for item in value) + "]"
    return tomli_w.dumps({"v": value}).removeprefix("v = ").strip()
