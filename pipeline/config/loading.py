"""Building a config: preset -> TOML file -> `--set key=value` overrides -> dataset defaults.

A config is built once, validated, written into the run folder and never mutated afterwards.
"""

from __future__ import annotations

import math
import os
import tomllib
import typing
from collections.abc import Callable
from dataclasses import fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Literal

import tomli_w

from pipeline.config.choices import did_you_mean, nearest, unknown_name
from pipeline.config.schema import DATASET_DEFAULTS, PRESET_TRACKING, PRESETS, Config
from pipeline.errors import UserError


def preset_config(name: str) -> Config:
    if name not in PRESETS:
        raise unknown_name("preset", name, PRESETS)
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
            hint_text = did_you_mean(nearest(str(raw), choices))
            raise UserError(
                f"bad value for '{key}': {raw!r}"
                + (f": {hint_text}" if hint_text else "")
                + f" (choose from {', '.join(choices)})"
            )
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


def config_keys(config: Config | None = None) -> list[str]:
    """Every dotted key a config takes (`tracking.iters`, ...), section by section."""
    config = config or Config()
    return [
        f"{section.name}.{item.name}"
        for section in fields(config)
        if is_dataclass(value := getattr(config, section.name))
        for item in fields(value)
    ]


def unknown_key(key: str) -> UserError:
    """`unknown config key 'tracking.iterz': did you mean 'tracking.iters'?`, pointing at the
    section's listing (or the list of sections) rather than printing every key."""
    keys = config_keys()
    last = key.rsplit(".", 1)[-1]
    candidates = [k for k in keys if k.endswith(f".{last}")][:2] or nearest(key, keys)
    sections = sorted({k.split(".")[0] for k in keys})
    section = key.split(".")[0]
    where = f"gsplatam config {section}" if section in sections else "gsplatam config"
    hint = did_you_mean(candidates)
    return UserError(f"unknown config key '{key}'" + (f": {hint}" if hint else "") + f" (every key: {where})")


def with_value(config: Config, key: str, raw: Any) -> Config:
    """A copy of `config` with the dotted `key` (e.g. 'tracking.iters') set to `raw`."""
    *path, last = key.split(".")

    def update(node: Any, depth: int) -> Any:
        names = {f.name for f in fields(node)}
        name = path[depth] if depth < len(path) else last
        if name not in names or name == "preset":
            raise unknown_key(key)
        child = getattr(node, name)
        if depth < len(path):
            if not is_dataclass(child):
                raise unknown_key(key)
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


def with_absolute_dataset_path(config: Config) -> Config:
    """`dataset.path` made absolute (a run folder's config.toml then works from any directory),
    the folder as it was given kept in `dataset.path_as_given` (the one recorded first, when the
    config already holds one)."""
    path = config.dataset.path
    if not path:
        return config
    given = path if not os.path.isabs(path) else (config.dataset.path_as_given or path)
    absolute = os.path.abspath(os.path.expanduser(path))
    return replace(config, dataset=replace(config.dataset, path=absolute, path_as_given=given))


def _port(port: int, off: bool = False) -> bool:
    return (off and port == 0) or 1 <= port <= 65535


def _negative_learning_rate(config: Config) -> str | None:
    """The key of the first negative learning rate, if any (NaN is refused when read)."""
    for name, section in (("tracking", config.tracking), ("mapping", config.mapping)):
        for item in fields(section):
            if item.name.startswith("lr_") and getattr(section, item.name) < 0:
                return f"{name}.{item.name}"
    return None


MAX_SYNTHETIC_SIDE = 4096  # pixels: a generated frame's width and height at most (4K)
MAX_SYNTHETIC_FRAMES = 100_000  # frames of a generated sequence at most (~55 min at 30 frames/s)
MAX_TIME_JITTER_S = 0.08  # a TUM reader pairs colour, depth and pose at most this far apart (tum.MAX_DT)


def _finite(value: float) -> bool:
    return math.isfinite(value)


# The generated sequence's settings: (field, test, what it must be). `gsplatam synth` names a
# failed one by its option (--fps), a config by its key (synthetic.fps). NaN fails every test.
SYNTHETIC_LIMITS: tuple[tuple[str, Callable[[Any], bool], str], ...] = (
    ("frames", lambda v: 0 <= v <= MAX_SYNTHETIC_FRAMES, f"must be 0 (by device) to {MAX_SYNTHETIC_FRAMES:,}"),
    ("width", lambda v: 0 <= v <= MAX_SYNTHETIC_SIDE, f"must be 0 (by device) to {MAX_SYNTHETIC_SIDE} pixels"),
    ("height", lambda v: 0 <= v <= MAX_SYNTHETIC_SIDE, f"must be 0 (by device) to {MAX_SYNTHETIC_SIDE} pixels"),
    ("seed", lambda v: v >= 0, "must be >= 0"),
    ("speed", lambda v: _finite(v) and 0 < v <= 10, "must be > 0 and at most 10 (metres per second)"),
    ("jitter", lambda v: _finite(v) and 0 <= v <= 1, "must be 0 to 1 (metres of shake)"),
    ("fps", lambda v: _finite(v) and 0 < v <= 1000, "must be > 0 and at most 1000 (frames per second)"),
    ("depth_noise", lambda v: _finite(v) and 0 <= v <= 1, "must be 0 to 1 (noise std = k x depth^2)"),
    ("holes", lambda v: _finite(v) and 0 <= v < 1, "must be >= 0 and < 1 (a fraction of the depth pixels)"),
    (
        "time_jitter",
        lambda v: _finite(v) and 0 <= v < MAX_TIME_JITTER_S,
        f"must be >= 0 and < {MAX_TIME_JITTER_S} s (TUM pairs images at most that far apart)",
    ),
    ("loops", lambda v: 0 <= v <= 1000, "must be 0 to 1000"),
)


def synthetic_problem(synthetic: Any) -> tuple[str, Any, str] | None:
    """The first setting of a SyntheticConfig outside its limits: (field, value, what it must
    be); None when all are within them."""
    for name, ok, requirement in SYNTHETIC_LIMITS:
        value = getattr(synthetic, name)
        if not ok(value):
            return name, value, requirement
    return None


def _in_unit(value: float, closed: bool = True) -> bool:
    return 0 <= value <= 1 if closed else 0 <= value < 1


def validate(config: Config) -> None:
    """UserError naming the first setting out of its range (NaN is refused when read)."""
    problem = synthetic_problem(config.synthetic)
    if problem is not None:
        name, value, requirement = problem
        raise UserError(f"synthetic.{name} {requirement}, not {value}")
    negative_rate = _negative_learning_rate(config)
    dataset, live = config.dataset, config.live
    tracking, mapping, loops = config.tracking, config.mapping, config.loops
    checks = [
        (config.slam.backend_timeout_s > 0, "slam.backend_timeout_s must be > 0"),
        (config.gaussians.seed_scale > 0, "gaussians.seed_scale must be > 0 (footprints of a pixel)"),
        (0 < config.gaussians.seed_opacity < 1, "gaussians.seed_opacity must be in (0, 1)"),
        (dataset.depth_scale >= 0, "dataset.depth_scale must be > 0 (depth units per metre; 0: by layout)"),
        (
            len(dataset.depth_range_m) == 0
            or (len(dataset.depth_range_m) == 2 and 0 <= dataset.depth_range_m[0] < dataset.depth_range_m[1]),
            "dataset.depth_range_m takes two depths, nearest then farthest, metres (empty: no check)",
        ),
        (dataset.end == -1 or dataset.end > dataset.start, "dataset.end must be -1 (to the end) or > dataset.start"),
        (config.run.renders >= 0, "run.renders must be >= 0"),
        (
            "/" not in config.run.name and config.run.name not in (".", ".."),
            f"run.name (--name) must be a folder name under run.output, without '/', not '{config.run.name}'",
        ),
        (mapping.final_iters >= 0, "mapping.final_iters must be >= 0"),
        (mapping.refine_between >= 0, "mapping.refine_between must be >= 0"),
        (mapping.refine_pose_lr >= 0, "mapping.refine_pose_lr must be >= 0 (a learning rate)"),
        (mapping.final_pose_lr >= 0, "mapping.final_pose_lr must be >= 0 (a learning rate)"),
        (_in_unit(mapping.ssim_weight), "mapping.ssim_weight must be in [0, 1]"),
        (_in_unit(mapping.prune_opacity), "mapping.prune_opacity must be in [0, 1]"),
        (mapping.prune_scale_factor > 0, "mapping.prune_scale_factor must be > 0"),
        (min(mapping.prune_at, default=0) >= 0, "mapping.prune_at takes mapping iterations, each >= 0"),
        (mapping.scene_radius_divisor >= 0, "mapping.scene_radius_divisor must be >= 0 (0: by dataset)"),
        (_in_unit(tracking.silhouette_threshold), "tracking.silhouette_threshold must be in [0, 1]"),
        (tracking.lost_translation_m > 0, "tracking.lost_translation_m must be > 0"),
        (_in_unit(tracking.lost_coverage), "tracking.lost_coverage must be in [0, 1]"),
        (_in_unit(config.densify.silhouette_threshold), "densify.silhouette_threshold must be in [0, 1]"),
        (config.densify.depth_error_factor > 0, "densify.depth_error_factor must be > 0"),
        (loops.radius_m > 0, "loops.radius_m must be > 0"),
        (0 < loops.max_angle_deg <= 180, "loops.max_angle_deg must be in (0, 180]"),
        (_in_unit(loops.min_overlap), "loops.min_overlap must be in [0, 1]"),
        (-1 <= loops.min_similarity <= 1, "loops.min_similarity must be in [-1, 1] (a correlation)"),
        (_in_unit(loops.min_coverage), "loops.min_coverage must be in [0, 1]"),
        (_in_unit(loops.min_inliers), "loops.min_inliers must be in [0, 1]"),
        (
            min(loops.max_residual_m, loops.max_intensity_rms) > 0,
            "loops.max_residual_m and max_intensity_rms must be > 0",
        ),
        (_in_unit(loops.min_conditioning, closed=False), "loops.min_conditioning must be in [0, 1)"),
        (min(loops.agree_m, loops.agree_deg) > 0, "loops.agree_m and agree_deg must be > 0"),
        (loops.max_iterations >= 1, "loops.max_iterations must be >= 1"),
        (negative_rate is None, f"{negative_rate} must be >= 0 (a learning rate)"),
        (config.loss.color_weight >= 0 and config.loss.depth_weight >= 0, "loss weights must be >= 0"),
        (all(v > 0 for v in dataset.intrinsics), "dataset.intrinsics fx,fy,cx,cy must be positive"),
        (dataset.width >= 0 and dataset.height >= 0, "dataset.width and dataset.height must be >= 0 (0: native)"),
        (live.width >= 0 and live.height >= 0, "live.width and live.height must be >= 0 (0: the first frame's)"),
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
        (
            1 <= len(config.tracking.align_wide_iters) <= 7 and min(config.tracking.align_wide_iters, default=0) >= 1,
            "tracking.align_wide_iters takes 1 to 7 iteration counts (one per pyramid level, coarse to fine), each >= 1",
        ),
        (
            min(config.tracking.align_large_step_m, config.tracking.align_large_step_deg) > 0,
            "tracking.align_large_step_m and align_large_step_deg must be > 0",
        ),
        (config.tracking.align_max_renders >= 1, "tracking.align_max_renders must be >= 1"),
        (0 <= config.tracking.align_grid_m < 1, "tracking.align_grid_m must be in [0, 1) metres"),
        (config.tracking.relocalise_candidates >= 0, "tracking.relocalise_candidates must be >= 0"),
        (config.mapping.iters >= 0, "mapping.iters must be >= 0"),
        (config.mapping.window >= 2, "mapping.window must be >= 2"),
        (
            config.mapping.adjust_window == 0 or config.mapping.adjust_window >= 2,
            "mapping.adjust_window must be 0 or >= 2",
        ),
        (
            config.mapping.adjust_iters >= 1 and config.mapping.adjust_pose_lr > 0,
            "mapping.adjust_iters must be >= 1 and mapping.adjust_pose_lr > 0",
        ),
        (config.mapping.adjust_converged >= 0, "mapping.adjust_converged must be >= 0"),
        (config.slam.max_lead >= 0, "slam.max_lead must be >= 0"),
        (config.mapping.views_per_step >= 1, "mapping.views_per_step must be >= 1"),
        (config.keyframes.max_kept == 0 or config.keyframes.max_kept >= 2, "keyframes.max_kept must be 0 or >= 2"),
        (config.mapping.max_gaussians >= 0, "mapping.max_gaussians must be >= 0"),
        (config.live.max_keyframes >= 2 and config.live.max_gaussians >= 1, "live bounds must be positive"),
        (config.keyframes.every >= 1, "keyframes.every must be >= 1"),
        (config.keyframes.overlap_samples >= 1, "keyframes.overlap_samples must be >= 1"),
        (_in_unit(config.keyframes.min_overlap), "keyframes.min_overlap must be in [0, 1]"),
        (config.keyframes.max_translation > 0, "keyframes.max_translation must be > 0"),
        (_in_unit(config.keyframes.min_coverage), "keyframes.min_coverage must be in [0, 1]"),
        (config.loops.min_keyframes_back >= 2, "loops.min_keyframes_back must be >= 2"),
        (config.loops.max_candidates >= 1, "loops.max_candidates must be >= 1"),
        (config.loops.confirm_keyframes >= 0, "loops.confirm_keyframes must be >= 0"),
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
