"""Exports of a run folder: nerfstudio, .splat, full PLY, point cloud and mesh, read back by
third-party readers (plyfile, Open3D) and checked against what the run holds."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import GT_ROOM as ROOM
from conftest import needs_extra, write_gt_run

from pipeline.app.cli import main
from pipeline.app.export import export_run
from pipeline.geometry import quat_to_rotmat
from pipeline.io.outputs.exports.nerfstudio import DEPTH_UNITS_PER_METRE
from pipeline.io.outputs.exports.splat import SPLAT_RECORD
from pipeline.io.outputs.ply import read_ply
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.io.sources.datasets.synthetic import distance_to_surfaces, make_scene, trajectory
from pipeline.slam.state import Checkpoint

plyfile = pytest.importorskip("plyfile", reason="plyfile is a test dependency (pip install -e '.[test]')")


@pytest.fixture(scope="module")
def gt_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_gt_run(tmp_path_factory.mktemp("exports"))


def _checkpoint(run: Path) -> Checkpoint:
    return RunFolder(run).read_checkpoint()[0]


def test_nerfstudio_transforms_hold_opengl_camera_to_world_and_metric_depth(gt_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "ns"
    assert main(["export", str(gt_run), "--to", "nerfstudio", "--output", str(out)]) == 0
    meta = json.loads((out / "transforms.json").read_text())
    assert {"fl_x", "fl_y", "cx", "cy", "w", "h", "frames", "ply_file_path"} <= set(meta)
    assert (meta["w"], meta["h"]) == (ROOM.width, ROOM.height)
    checkpoint = _checkpoint(gt_run)
    assert len(meta["frames"]) == len(checkpoint.keyframes)
    point = checkpoint.gaussians.means[0].double().numpy()
    for entry, keyframe in zip(meta["frames"], checkpoint.keyframes):
        c2w_gl = np.array(entry["transform_matrix"])
        c2w_cv = keyframe.c2w.double().numpy()
        assert np.allclose(c2w_gl @ np.diag([1.0, -1, -1, 1]), c2w_cv, atol=1e-6)  # round trip
        # The same world point lands on the same pixel by nerfstudio's convention (camera looks
        # down -z, y up) and by OpenCV's (z forward, y down).
        x, y, z = (np.linalg.inv(c2w_gl) @ np.append(point, 1.0))[:3]
        u_gl, v_gl = meta["fl_x"] * x / -z + meta["cx"], -meta["fl_y"] * y / -z + meta["cy"]
        xc, yc, zc = (np.linalg.inv(c2w_cv) @ np.append(point, 1.0))[:3]
        assert np.allclose([u_gl, v_gl], [meta["fl_x"] * xc / zc + meta["cx"], meta["fl_y"] * yc / zc + meta["cy"]])
        image = cv2.imread(str(out / entry["file_path"]))
        depth = cv2.imread(str(out / entry["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert image.shape == (ROOM.height, ROOM.width, 3) and depth.dtype == np.uint16
        assert np.abs(depth / DEPTH_UNITS_PER_METRE - keyframe.depth.numpy()).max() <= 0.5e-3 + 1e-6  # mm rounding
    points = plyfile.PlyData.read(str(out / meta["ply_file_path"]))["vertex"]
    assert points.count == len(checkpoint.gaussians)


def test_splat_is_32_bytes_per_gaussian_most_visible_first(gt_run: Path, tmp_path: Path) -> None:
    assert main(["export", str(gt_run), "--to", "splat", "--output", str(tmp_path / "m.splat")]) == 0
    data = (tmp_path / "m.splat").read_bytes()
    gaussians = _checkpoint(gt_run).gaussians
    assert len(data) == 32 * len(gaussians)
    records = np.frombuffer(data, dtype=SPLAT_RECORD)
    scales = gaussians.scales().numpy()
    opacity = torch.sigmoid(gaussians.opacity_logits).numpy()
    importance = np.prod(records["scale"], axis=1) * records["rgba"][:, 3]
    assert np.all(np.diff(importance) <= 1e-6 * importance.max())  # sorted, most visible first
    order = np.lexsort(records["position"].T)
    expected = np.lexsort(gaussians.means.numpy().T)
    assert np.allclose(records["position"][order], gaussians.means.numpy()[expected])
    assert np.allclose(records["scale"][order], scales[expected], rtol=1e-6)
    assert np.abs(records["rgba"][order, 3] / 255.0 - opacity[expected]).max() <= 0.5 / 255 + 1e-6
    unit = (records["rotation"].astype(np.float64) - 128) / 128
    assert np.allclose(unit[:, 0], 1.0, atol=1 / 128) and np.abs(unit[:, 1:]).max() <= 1 / 128  # identity


def test_full_ply_has_normals_and_zero_f_rest_and_reads_back(gt_run: Path, tmp_path: Path) -> None:
    path = tmp_path / "full.ply"
    assert main(["export", str(gt_run), "--to", "ply", "--output", str(path)]) == 0
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    names = [p.name for p in vertex.properties]
    assert names[:6] == ["x", "y", "z", "nx", "ny", "nz"]
    rest = [f"f_rest_{i}" for i in range(45)]
    assert [n for n in names if n.startswith("f_rest_")] == rest
    assert all(np.all(vertex[n] == 0) for n in rest)
    gaussians = _checkpoint(gt_run).gaussians
    assert np.allclose(vertex["x"], gaussians.means[:, 0].numpy())
    assert np.allclose(read_ply(path).colors.numpy(), gaussians.colors.numpy(), atol=1e-6)


def test_normals_are_the_flat_axis_of_2d_and_the_shortest_of_anisotropic_gaussians() -> None:
    from pipeline.io.outputs.exports.full_ply import surface_normals
    from pipeline.render import Gaussians

    quats = torch.tensor([[0.9, 0.1, -0.3, 0.2], [1.0, 0.0, 0.0, 0.0]])
    log_scales = torch.log(torch.tensor([[0.3, 0.01, 0.2], [0.1, 0.2, 0.05]]))
    g = Gaussians(torch.zeros(2, 3), quats, log_scales, torch.zeros(2), torch.zeros(2, 3))
    rotation = quat_to_rotmat(quats)
    assert torch.allclose(surface_normals(g, "3d"), torch.stack([rotation[0, :, 1], rotation[1, :, 2]]))
    assert torch.allclose(surface_normals(g, "2d"), rotation[:, :, 2])
    isotropic = Gaussians(g.means, quats, log_scales[:, :1], g.opacity_logits, g.colors)
    assert torch.count_nonzero(surface_normals(isotropic, "3d")) == 0


def test_pointcloud_holds_the_centres_with_their_colours(gt_run: Path, tmp_path: Path) -> None:
    path = tmp_path / "points.ply"
    assert main(["export", str(gt_run), "--to", "pointcloud", "--output", str(path)]) == 0
    vertex = plyfile.PlyData.read(str(path))["vertex"]
    gaussians = _checkpoint(gt_run).gaussians
    assert vertex["red"].dtype == np.uint8 and vertex.count == len(gaussians)
    rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1) / 255.0
    assert np.abs(rgb - gaussians.colors.numpy()).max() <= 0.5 / 255 + 1e-6
    assert np.allclose(np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1), gaussians.means.numpy())


def _mesh_to_room_cm(vertices: torch.Tensor, run: Path) -> tuple[float, float]:
    """Chamfer-type distances (cm) between mesh vertices [V, 3] (the run's frame) and the room:
    accuracy, the mean distance of the vertices to the nearest true surface; completeness, the
    mean distance of the surface points the keyframes saw (their exact depth) to the nearest vertex."""
    first = torch.from_numpy(trajectory(ROOM, ROOM.frames)[0]).float()  # the run's frame -> the room's
    in_room = vertices @ first[:3, :3].T + first[:3, 3]
    accuracy = distance_to_surfaces(make_scene(ROOM.seed), in_room).mean().item()
    checkpoint, camera = _checkpoint(run), RunFolder(run).read_intrinsics()
    seen = []
    for keyframe in checkpoint.keyframes:
        v, u = torch.nonzero(keyframe.depth > 0, as_tuple=True)
        z = keyframe.depth[v, u]
        rays = torch.stack([(u + 0.5 - camera.cx) / camera.fx, (v + 0.5 - camera.cy) / camera.fy, torch.ones_like(z)])
        seen.append((keyframe.c2w[:3, :3] @ (rays * z) + keyframe.c2w[:3, 3:]).T)
    nearest = torch.cat([torch.cdist(chunk, vertices).amin(dim=1) for chunk in torch.cat(seen).split(2048)])
    return 100 * accuracy, 100 * nearest.mean().item()


def test_tsdf_fusion_of_exact_views_lies_on_the_rooms_surfaces(gt_run: Path) -> None:
    """The fusion alone, fed the room's exact depth at its exact poses (pixel centres, pose and
    depth conventions all enter this). A 64x48 pixel spans 5-10 cm at these depths and the
    projective TSDF steps by pixels, so at 2 cm voxels the mesh lies 2.2 cm from the true
    surfaces on average and covers what was seen to 4.7 cm (measured); bounds: 3 and 6 cm."""
    needs_extra("open3d")
    from pipeline.io.outputs.exports.mesh import RGBDView, fuse_tsdf

    checkpoint, camera = _checkpoint(gt_run), RunFolder(gt_run).read_intrinsics()
    views = [RGBDView(k.color_u8.numpy(), k.depth.numpy(), k.c2w.double().numpy()) for k in checkpoint.keyframes]
    mesh = fuse_tsdf(views, camera, voxel_m=0.02, max_depth_m=10.0)
    accuracy_cm, completeness_cm = _mesh_to_room_cm(torch.from_numpy(mesh.vertices), gt_run)
    print(f"exact views: mesh accuracy {accuracy_cm:.2f} cm, completeness {completeness_cm:.2f} cm")
    assert accuracy_cm < 3.0 and completeness_cm < 6.0


def test_mesh_export_fuses_the_maps_rendered_depth_onto_the_room(gt_run: Path, tmp_path: Path) -> None:
    """The command: depth rendered from the map at the keyframes, fused, written as PLY. The map
    here is one Gaussian per pixel of two 64x48 frames (no optimisation); its rendered depth
    lies ~15 cm short on slanted surfaces, where front-to-back blending of pixel-sized
    Gaussians favours the nearer neighbours, so the bound is 20 cm each way: what it checks is
    a mesh where the room is (not mirrored, shifted or scaled: those give metres)."""
    needs_extra("open3d")
    path = tmp_path / "mesh.ply"
    assert main(["export", str(gt_run), "--to", "mesh", "--output", str(path), "--voxel", "0.03"]) == 0
    mesh = plyfile.PlyData.read(str(path))
    assert mesh["face"].count > 500 and {"nx", "red"} <= {p.name for p in mesh["vertex"].properties}
    vertices = torch.from_numpy(np.stack([mesh["vertex"][a] for a in "xyz"], axis=1).astype(np.float32))
    accuracy_cm, completeness_cm = _mesh_to_room_cm(vertices, gt_run)
    print(f"rendered views: mesh accuracy {accuracy_cm:.2f} cm, completeness {completeness_cm:.2f} cm")
    assert accuracy_cm < 20.0 and completeness_cm < 20.0


def test_export_errors_name_the_folder_or_file(gt_run: Path, tmp_path: Path, capsys) -> None:
    assert main(["export", str(tmp_path), "--to", "splat"]) == 2
    assert f"{tmp_path} is not a run folder" in capsys.readouterr().err
    broken = tmp_path / "run"
    broken.mkdir()
    (broken / "checkpoint.safetensors").write_bytes((gt_run / "checkpoint.safetensors").read_bytes())
    assert main(["export", str(broken), "--to", "nerfstudio"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no intrinsics.json in" in err[0]
    (broken / "intrinsics.json").write_text('{"fx": 1}')
    assert main(["export", str(broken), "--to", "nerfstudio"]) == 2
    assert "intrinsics.json is not a camera description" in capsys.readouterr().err
    assert main(["export", str(gt_run), "--to", "mesh", "--voxel", "0"]) == 2
    assert "--voxel must be positive" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["export", str(gt_run), "--to", "obj"])
    assert exit_info.value.code == 2


def test_export_defaults_to_the_run_folder(gt_run: Path) -> None:
    exported = export_run(gt_run, "pointcloud")
    assert exported.path == gt_run / "pointcloud.ply" and exported.path.is_file()


def _one_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err) and len(err) == 1
    return err[0]


def _state(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize(
    "fmt, name",
    [("splat", "map.ply"), ("ply", "checkpoint.safetensors"), ("pointcloud", "config.toml"),
     ("pointcloud", ".gsplatam-run"), ("splat", "recording/rgb.txt"), ("pointcloud", "../run/frames.csv")],
)  # fmt: skip
def test_an_export_never_writes_onto_the_runs_own_files(
    gt_run: Path, capsys: pytest.CaptureFixture[str], fmt: str, name: str
) -> None:
    before = _state(gt_run)
    assert main(["export", str(gt_run), "--to", fmt, "--output", str(gt_run / name)]) == 2
    line = _one_line(capsys)
    assert f"of the run folder {gt_run.resolve()}'s own files: an export never writes onto a run" in line
    assert _state(gt_run) == before


@pytest.mark.parametrize("fmt", ["splat", "pointcloud", "nerfstudio"])
def test_export_output_of_the_wrong_kind_is_one_line_naming_it(
    gt_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: str
) -> None:
    (tmp_path / "afile").write_text("mine")
    (tmp_path / "adir").mkdir()
    (tmp_path / "adir" / "notes.txt").write_text("mine")
    wrong = {"splat": tmp_path / "afile" / "m.splat", "pointcloud": tmp_path / "adir", "nerfstudio": tmp_path / "afile"}
    said = {"splat": "is a file, not a folder", "pointcloud": "is a folder", "nerfstudio": "is a file"}
    assert main(["export", str(gt_run), "--to", fmt, "--output", str(wrong[fmt])]) == 2
    line = _one_line(capsys)
    assert said[fmt] in line and str(tmp_path / ("adir" if fmt == "pointcloud" else "afile")) in line
    assert (tmp_path / "afile").read_text() == "mine" and (tmp_path / "adir" / "notes.txt").read_text() == "mine"


def test_nerfstudio_never_replaces_a_folder_of_the_users(
    gt_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "adir").mkdir()
    (tmp_path / "adir" / "notes.txt").write_text("mine")
    assert main(["export", str(gt_run), "--to", "nerfstudio", "--output", str(tmp_path / "adir")]) == 2
    assert "holds files that are not a nerfstudio export" in _one_line(capsys)
    assert [p.name for p in (tmp_path / "adir").iterdir()] == ["notes.txt"]


def test_a_nerfstudio_export_on_a_full_disk_leaves_the_earlier_export_whole(
    gt_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno
    import os

    out = tmp_path / "ns"
    assert main(["export", str(gt_run), "--to", "nerfstudio", "--output", str(out)]) == 0
    capsys.readouterr()
    earlier = _state(out)

    def full(*args: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr("pipeline.io.outputs.exports.nerfstudio.write_pointcloud", full)
    assert main(["export", str(gt_run), "--to", "nerfstudio", "--output", str(out)]) == 2
    assert _one_line(capsys) == f"gsplatam: error: cannot write {out}: No space left on device"
    assert _state(out) == earlier and sorted(p.name for p in tmp_path.iterdir()) == ["ns"]  # no half folder left
    assert main(["export", str(gt_run), "--to", "nerfstudio", "--output", str(tmp_path / "new")]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ns"]


@pytest.mark.parametrize("fmt", ["splat", "pointcloud", "ply"])
def test_an_export_of_a_tampered_checkpoint_is_one_line(
    gt_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: str
) -> None:
    import shutil

    from conftest import tamper_checkpoint

    run = tmp_path / "run"
    shutil.copytree(gt_run, run)
    tamper_checkpoint(run / "checkpoint.safetensors", "gaussians.means", "one axis fewer")
    before = _state(run)
    assert main(["export", str(run), "--to", fmt]) == 2
    assert "gaussians.means has shape" in _one_line(capsys)
    assert _state(run) == before
