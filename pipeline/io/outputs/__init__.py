"""What a run writes: the run folder, the map (PLY), trajectories and the checkpoint."""
