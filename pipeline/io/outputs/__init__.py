"""What a run leaves: the run folder and its records, the checkpoint, the map (PLY), periodic saves and exports."""
