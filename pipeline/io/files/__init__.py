"""Ground-floor file handling that every layer uses: atomic writes, folders, image files and TUM trajectories."""
