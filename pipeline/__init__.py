"""gsplatam: real-time RGB-D SLAM with Gaussian splatting (SplaTAM rebuilt on gsplat)."""

__version__ = "0.2.0"
