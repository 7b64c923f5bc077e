"""Writers that take a run elsewhere, one module per format, and their registry: a new format is
a writer module (what `Exporter` in job.py asks of it) plus one line in EXPORTERS. The export
command's choices and help, the commands a run's summary suggests, the run folder's names and
docs/exports.md's table (tests/io/outputs/test_export_registry.py) all read EXPORTERS."""

from pipeline.io.outputs.exports import compressed_ply, full_ply, mesh, nerfstudio, pointcloud, splat, spz
from pipeline.io.outputs.exports.job import Exporter

# `gsplatam export --to NAME` -> its writer, in the order the help and the docs list them
EXPORTERS: dict[str, Exporter] = {
    "nerfstudio": nerfstudio,
    "splat": splat,
    "ply": full_ply,
    "compressed-ply": compressed_ply,
    "spz": spz,
    "mesh": mesh,
    "pointcloud": pointcloud,
}
