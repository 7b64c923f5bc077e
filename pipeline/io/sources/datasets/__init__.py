"""Datasets on disk (Replica, TUM) and the generated synthetic room."""
