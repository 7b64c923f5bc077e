from __future__ import annotations

import re
from pathlib import Path

import pytest

from pipeline.config import PRESET_TRACKING, PRESETS, load_config, preset_config, to_toml, with_dataset_defaults
from pipeline.errors import UserError


@pytest.mark.parametrize(
    "name, numbers",
    [("base", (40, 60, 24, 5)), ("small", (10, 15, 15, 5)), ("tiny", (4, 6, 6, 5)), ("tum", (200, 30, 20, 5))],
)
def test_presets_have_the_specified_numbers(name: str, numbers: tuple[int, int, int, int]) -> None:
    config = preset_config(name)
    assert (config.tracking.iters, config.mapping.iters, config.mapping.window, config.keyframes.every) == numbers


def test_the_tracking_method_follows_the_preset_and_can_be_chosen() -> None:
    assert {name: preset_config(name).tracking.method for name in PRESETS} == PRESET_TRACKING
    assert PRESET_TRACKING["tiny"] == PRESET_TRACKING["small"] == "align"
    assert load_config("tiny", overrides=["tracking.method=adam"]).tracking.method == "adam"
    config = load_config("base", overrides=["tracking.method=align", "tracking.align_iters=8,4"])
    assert config.tracking.method == "align" and config.tracking.align_iters == (8, 4)


def test_shared_defaults() -> None:
    c = preset_config("base")
    assert c.tracking.lr_translation == 0.002
    assert (c.mapping.lr_means, c.mapping.lr_colors, c.mapping.lr_rotations) == (1e-4, 2.5e-3, 1e-3)
    assert (c.mapping.lr_opacities, c.mapping.lr_scales) == (5e-2, 1e-3)
    assert (c.loss.color_weight, c.loss.depth_weight) == (0.5, 1.0)
    assert c.tracking.silhouette_threshold == 0.99
    assert (c.densify.silhouette_threshold, c.densify.depth_error_factor) == (0.5, 50.0)
    assert c.keyframes.overlap_samples == 1600
    assert (c.mapping.prune_opacity, c.mapping.prune_scale_factor, c.mapping.prune_at) == (0.005, 0.1, (0, 20))
    assert (c.gaussians.kind, c.gaussians.isotropic) == ("3d", True)


def test_dataset_defaults_fill_only_unset_values() -> None:
    replica = with_dataset_defaults(preset_config("base"), "replica")
    tum = with_dataset_defaults(preset_config("tum"), "tum")
    assert (replica.tracking.lr_rotation, replica.mapping.scene_radius_divisor) == (0.0004, 3.0)
    assert (tum.tracking.lr_rotation, tum.mapping.scene_radius_divisor) == (0.002, 2.0)
    chosen = with_dataset_defaults(load_config("base", overrides=["tracking.lr_rotation=0.01"]), "tum")
    assert chosen.tracking.lr_rotation == 0.01


def test_overrides_are_typed_and_last_wins() -> None:
    config = load_config(
        "tiny", overrides=["tracking.iters=7", "gaussians.isotropic=false", "render.eps2d=0.1", "tracking.iters=9"]
    )
    assert config.tracking.iters == 9 and config.gaussians.isotropic is False and config.render.eps2d == 0.1
    config = load_config("tiny", overrides=["dataset.intrinsics=1,2,3,4", "mapping.prune_at=0 10 20"])
    assert config.dataset.intrinsics == (1.0, 2.0, 3.0, 4.0) and config.mapping.prune_at == (0, 10, 20)


def test_toml_file_round_trip(tmp_path) -> None:
    config = load_config("small", overrides=["tracking.iters=3", "run.name=abc", "gaussians.kind=2d"])
    path = tmp_path / "c.toml"
    path.write_text(to_toml(config))
    assert load_config("base", path) == config


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["tracking.itres=3"], "unknown config key 'tracking.itres'"),
        (["nosection.iters=3"], "unknown config key 'nosection.iters'"),
        (["tracking.iters=many"], "bad value for 'tracking.iters'"),
        (["tracking.iters=2.5"], "bad value for 'tracking.iters'"),
        (["gaussians.kind=4d"], "bad value for 'gaussians.kind'"),
        (["gaussians.isotropic=maybe"], "bad value for 'gaussians.isotropic'"),
        (["tracking"], "bad --set 'tracking'"),
        (["tracking=3"], "'tracking' is a section"),
        (["mapping.window=1"], "mapping.window must be >= 2"),
        (["loops.enabled=true", "loops.max_candidates=0"], "loops.max_candidates must be >= 1"),
        (["tracking.method=icp"], "bad value for 'tracking.method': 'icp' (choose from adam, align)"),
        (["tracking.method=alig"], "bad value for 'tracking.method': 'alig': did you mean 'align'? (choose from"),
        (["tracking.iterz=3"], "unknown config key 'tracking.iterz': did you mean 'tracking.iters'"),
        (["trackin.iters=3"], "unknown config key 'trackin.iters': did you mean 'tracking.iters'"),
        (["tracking.final_iters=3"], "did you mean 'mapping.final_iters'?"),
        (["tracking.refine_iters=-1"], "tracking.refine_iters must be >= 0"),
        (["tracking.align_iters=4,0,2"], "tracking.align_iters takes 1 to 6 iteration counts"),
        (["tracking.align_iters="], "tracking.align_iters takes 1 to 6 iteration counts"),
        (["tracking.align_color_sigma=0"], "tracking.align_depth_sigma_m and align_color_sigma must be > 0"),
        (["tracking.align_min_inliers=1.5"], "tracking.align_min_inliers must be in [0, 1]"),
        (["tracking.align_min_silhouette=1"], "tracking.align_min_silhouette must be in [0, 1)"),
        (["tracking.align_grid_m=-0.1"], "tracking.align_grid_m must be in [0, 1) metres"),
        (["tracking.lr_translation=nan"], "bad value for 'tracking.lr_translation': 'nan' (expected a finite number)"),
        (["mapping.lr_colors=inf"], "bad value for 'mapping.lr_colors'"),
        (["mapping.lr_means=-0.1"], "mapping.lr_means must be >= 0"),
        (["tracking.lr_rotation=-1e-3"], "tracking.lr_rotation must be >= 0"),
        (["loss.depth_weight=-1"], "loss weights must be >= 0"),
        (["dataset.width=-64", "dataset.height=-48"], "dataset.width and dataset.height must be >= 0"),
        (["live.width=-1", "live.height=-1"], "live.width and live.height must be >= 0"),
        (["synthetic.width=-8"], "synthetic.width must be 0 (by device) to 4096 pixels, not -8"),
        (["synthetic.fps=0"], "synthetic.fps must be > 0"),
        (["synthetic.holes=2"], "synthetic.holes must be >= 0 and < 1"),
        (["synthetic.loops=100000"], "synthetic.loops must be 0 to 1000"),
        (["mapping.final_iters=-5"], "mapping.final_iters must be >= 0"),
        (["mapping.final_pose_lr=-1e-3"], "mapping.final_pose_lr must be >= 0"),
        (["mapping.refine_between=-1"], "mapping.refine_between must be >= 0"),
        (["slam.backend_timeout_s=0"], "slam.backend_timeout_s must be > 0"),
        (["gaussians.seed_scale=0"], "gaussians.seed_scale must be > 0"),
        (["gaussians.seed_opacity=1"], "gaussians.seed_opacity must be in (0, 1)"),
        (["mapping.ssim_weight=1.5"], "mapping.ssim_weight must be in [0, 1]"),
        (["loops.min_similarity=-2"], "loops.min_similarity must be in [-1, 1]"),
        (["dataset.depth_scale=-1000"], "dataset.depth_scale must be > 0"),
        (["dataset.depth_range_m=5,1"], "dataset.depth_range_m takes two depths"),
        (["dataset.start=5", "dataset.end=5"], "dataset.end must be -1 (to the end) or > dataset.start"),
        (["run.renders=-1"], "run.renders must be >= 0"),
        (["run.name=../elsewhere"], "run.name (--name) must be a folder name under run.output, without '/'"),
        (["dataset.intrinsics=0,500,320,240"], "dataset.intrinsics fx,fy,cx,cy must be positive"),
        (["dataset.intrinsics=500,-500,320,240"], "dataset.intrinsics fx,fy,cx,cy must be positive"),
        (["live.status_port=65536"], "live.status_port must be a port, 1 to 65535"),
        (["live.status_port=-1"], "live.status_port must be a port"),
        (["viewer.port=0"], "viewer.port must be a port"),
        (["run.save_every_s=0"], "run.save_every_s must be > 0"),
        (["keyframes.min_overlap=1.2"], "keyframes.min_overlap must be in [0, 1]"),
        (["keyframes.max_translation=0"], "keyframes.max_translation must be > 0"),
        (["keyframes.min_coverage=-0.1"], "keyframes.min_coverage must be in [0, 1]"),
        (["mapping.rate=frames"], "bad value for 'mapping.rate': 'frames': did you mean 'frame'?"),
    ],
)
def test_bad_overrides_name_the_key(overrides: list[str], message: str) -> None:
    with pytest.raises(UserError, match=re.escape(message)):
        load_config("base", overrides=overrides)


def test_a_nan_in_a_config_file_names_its_key(tmp_path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[mapping]\nlr_opacities = nan\n")
    with pytest.raises(UserError, match="bad value for 'mapping.lr_opacities'"):
        load_config("tiny", path)


def test_unknown_preset() -> None:
    with pytest.raises(UserError, match="unknown preset 'huge'"):
        load_config("huge")
    with pytest.raises(UserError, match=re.escape("unknown preset 'tinny': did you mean 'tiny'? (choose from")):
        load_config("tinny")
    assert set(PRESETS) == {"base", "small", "tiny", "tum"}


def test_an_unknown_key_is_answered_with_the_nearest_not_with_every_key_of_its_section() -> None:
    with pytest.raises(UserError) as caught:
        load_config("tiny", overrides=["tracking.iterz=3"])
    message = str(caught.value)
    assert "did you mean 'tracking.iters'" in message and "gsplatam config tracking" in message
    assert "silhouette_threshold" not in message  # the section's other keys are not listed


def test_bad_config_file(tmp_path) -> None:
    with pytest.raises(UserError, match="config file not found"):
        load_config("base", tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[tracking\niters = 3")
    with pytest.raises(UserError, match="cannot read config file"):
        load_config("base", bad)


def test_live_input_defaults_to_the_preset_near_camera_rate() -> None:
    import torch

    from pipeline.devices import default_preset

    assert default_preset(torch.device("cuda")) == "base"
    assert default_preset(torch.device("cuda"), live=True) == "tiny"
    assert default_preset(torch.device("cpu")) == "tiny"


def _every_key(config) -> list[str]:
    """Dotted keys of every setting, from the TOML a run folder holds (its writer walks the schema)."""
    import tomllib

    keys = []
    for name, value in tomllib.loads(to_toml(config)).items():
        keys += [f"{name}.{key}" for key in value] if isinstance(value, dict) else [name]
    return keys


def _entries(out: str) -> dict[str, str]:
    """key -> its entry (key, type, default, meaning; a wrapped meaning's lines joined) from the
    config command's output."""
    entries: dict[str, str] = {}
    key = None
    for line in out.splitlines():
        if line.startswith("  ") and not line.startswith("   "):
            key = line.split()[0]
            entries[key] = line.strip()
        elif line.startswith("   ") and key is not None:
            entries[key] += " " + line.strip()
        else:
            key = None
    return entries


def test_the_config_command_lists_every_key_with_its_type_default_and_meaning(capsys) -> None:
    from pipeline.app.cli import main
    from pipeline.config.docs import LINE_WIDTH, config_sections

    assert main(["config", "--preset", "tiny"]) == 0
    out = capsys.readouterr().out
    assert max(len(line) for line in out.splitlines()) <= LINE_WIDTH
    entries = _entries(out)
    config = preset_config("tiny")
    docs = {k.key: k for section in config_sections(config) for k in section.keys}
    assert sorted(docs) == sorted(_every_key(config)) == sorted(entries)
    for key, doc in docs.items():
        assert doc.meaning and doc.type, key  # a comment on the field's line in schema.py
        entry = " ".join(entries[key].split())
        assert doc.type in entry and doc.default in entry and " ".join(doc.meaning.split()) in entry
    assert docs["tracking.iters"].default == "4" and docs["run.loader"].type == "pipelined|sync"
    assert docs["mapping.prune_at"].type == "list of int"


def test_the_config_command_shows_one_section_and_names_a_wrong_one(capsys) -> None:
    from pipeline.app.cli import main

    assert main(["config", "live"]) == 0
    out = capsys.readouterr().out
    assert "live.record" in out and "tracking.iters" not in out
    assert main(["config", "trackin"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown config section 'trackin': did you mean 'tracking'?" in err[0]
    assert main(["config", "final_iters"]) == 2
    assert "did you mean 'mapping.final_iters'?" in capsys.readouterr().err


def test_the_config_command_refuses_an_empty_preset(capsys) -> None:
    from pipeline.app.cli import main

    assert main(["config", "--preset", ""]) == 2
    assert "unknown preset ''" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["run", "config"])
def test_help_names_the_most_used_settings(command: str, capsys) -> None:
    from pipeline.app.cli import main
    from pipeline.app.commands.options import MOST_USED

    with pytest.raises(SystemExit):
        main([command, "--help"])
    out = capsys.readouterr().out
    assert "most used settings" in out and all(f"  {key}=" in out for key in MOST_USED)
    assert "dataset.depth_scale=0.0" in out and "millimetres: 1000" in " ".join(out.split())


def _shown(capsys: pytest.CaptureFixture[str]) -> dict[str, str]:
    """key -> its default, from the config command's output."""
    return {key: entry.split()[2] for key, entry in _entries(capsys.readouterr().out).items()}


@pytest.mark.parametrize("device, preset, method", [("cpu", "tiny", '"align"'), ("cuda", "base", '"adam"')])
def test_the_config_command_shows_the_defaults_run_would_use_on_this_device(
    device: str, preset: str, method: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import torch

    from pipeline import devices
    from pipeline.app.cli import main

    monkeypatch.setattr(devices, "resolve_device", lambda name: torch.device(device))
    assert main(["config"]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    assert f"preset '{preset}' on device {device}" in header and "picks for this device" in header
    assert main(["config", "mapping"]) == 0
    assert _shown(capsys)["mapping.iters"] == str(preset_config(preset).mapping.iters)
    assert main(["config", "tracking.method"]) == 0
    assert _shown(capsys) == {"tracking.method": method}


def test_the_config_command_shows_one_key_and_names_a_wrong_one(capsys: pytest.CaptureFixture[str]) -> None:
    from pipeline.app.cli import main

    assert main(["config", "--preset", "base", "mapping.iters"]) == 0
    assert _shown(capsys) == {"mapping.iters": "60"}
    assert main(["config", "preset", "--preset", "small"]) == 0
    assert _shown(capsys) == {"preset": '"small"'}
    assert main(["config", "tracking.nope"]) == 2
    assert "unknown config key 'tracking.nope'" in capsys.readouterr().err
    assert main(["config", "trackin.method"]) == 2
    assert "unknown config key 'trackin.method': did you mean 'tracking.method'?" in capsys.readouterr().err


def test_strings_that_need_toml_escapes_round_trip_through_config_toml(tmp_path: Path) -> None:
    from dataclasses import replace

    config = preset_config("tiny")
    odd = 'a "room"\twith\nlines \\ and \x07'
    config = replace(config, dataset=replace(config.dataset, path=odd))
    path = tmp_path / "config.toml"
    path.write_text(to_toml(config))
    assert load_config(config_file=path).dataset.path == odd
