"""Where frames come from: datasets on disk, the generated room and live cameras (below SLAM: they import none of it)."""
