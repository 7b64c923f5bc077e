"""The SplaTAM algorithm: Gaussian map, tracking, densification, keyframes and mapping."""
