"""The pipeline's stages: source -> decode -> upload -> SLAM -> sinks, joined by bounded queues."""
