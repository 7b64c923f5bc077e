"""Writers that take a run elsewhere, one module per format: nerfstudio, .splat, full 3DGS PLY,
compressed PLY, mesh, point cloud."""

# format -> where `gsplatam export` writes it by default, inside the run folder
FORMATS: dict[str, str] = {
    "nerfstudio": "nerfstudio",
    "splat": "map.splat",
    "ply": "map_3dgs.ply",
    "compressed-ply": "map.compressed.ply",
    "mesh": "mesh.ply",
    "pointcloud": "pointcloud.ply",
}
