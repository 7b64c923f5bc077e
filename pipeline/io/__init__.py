"""Where the pipeline meets the outside world, grouped by job: `sources` (datasets on disk, the
generated room, live cameras) feed SLAM from below; `outputs` (the run folder, the checkpoint,
exports) keep what SLAM made, from above; `files` (atomic writes, images, trajectories, graphs)
are the file formats both stand on."""
