"""Writers that take a run elsewhere, one module per format: nerfstudio, .splat, full 3DGS PLY,
compressed PLY, SPZ, mesh, point cloud."""

# format -> where `gsplatam export` writes it by default, inside the run folder
FORMATS: dict[str, str] = {
    "nerfstudio": "nerfstudio",
    "splat": "map.splat",
    "ply": "map_3dgs.ply",
    "compressed-ply": "map.compressed.ply",
    "spz": "map.spz",
    "mesh": "mesh.ply",
    "pointcloud": "pointcloud.ply",
}
