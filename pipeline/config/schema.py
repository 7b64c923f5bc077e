"""The configuration schema: one frozen dataclass per component, the presets and the values
SplaTAM tunes per dataset family. Loading, overriding and writing live in `loading.py`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

DatasetFormat = Literal["auto", "replica", "tum"]
GaussianKind = Literal["3d", "2d"]
RenderBackend = Literal["auto", "gsplat", "reference"]
LoaderKind = Literal["pipelined", "sync"]
Switch = Literal["auto", "on", "off"]


@dataclass(frozen=True)
class DatasetConfig:
    path: str = ""  # empty: generate the embedded synthetic scene
    format: DatasetFormat = "auto"
    width: int = 0  # 0: native size; otherwise resize (colour linear, depth nearest)
    height: int = 0
    start: int = 0
    end: int = -1  # exclusive; -1: to the end
    stride: int = 1
    intrinsics: tuple[float, ...] = ()  # (fx, fy, cx, cy) at the stored size; empty: from the layout


@dataclass(frozen=True)
class SyntheticConfig:
    """The embedded default scene; sizes of 0 are chosen by device (small on the CPU)."""

    frames: int = 0
    width: int = 0
    height: int = 0
    seed: int = 0
    speed: float = 0.3  # metres per second along the path
    jitter: float = 0.01  # metres (and radians x 0.5) of hand-held shake
    fps: float = 30.0
    layout: DatasetFormat = "replica"  # replica or tum
    depth_noise: float = 0.0  # TUM layout only: depth noise std = depth_noise x depth^2, metres
    holes: float = 0.0  # TUM layout only: fraction of depth pixels zeroed, in blobs
    time_jitter: float = 0.0  # TUM layout only: depth and pose timestamp offsets up to this, seconds


@dataclass(frozen=True)
class TrackingConfig:
    iters: int = 40
    lr_rotation: float = 0.0  # 0: by dataset (0.0004 Replica-like, 0.002 TUM)
    lr_translation: float = 0.002
    silhouette_threshold: float = 0.99
    lost_translation_m: float = 0.3  # a jump beyond this from the initial guess marks tracking lost
    lost_coverage: float = 0.05  # fewer pixels than this fraction above the threshold marks it lost


@dataclass(frozen=True)
class MappingConfig:
    iters: int = 60
    window: int = 24
    lr_means: float = 1e-4
    lr_colors: float = 2.5e-3
    lr_rotations: float = 1e-3
    lr_opacities: float = 5e-2
    lr_scales: float = 1e-3
    ssim_weight: float = 0.2
    prune_opacity: float = 0.005
    prune_scale_factor: float = 0.1  # x scene radius
    prune_at: tuple[int, ...] = (0, 20)
    scene_radius_divisor: float = 0.0  # 0: by dataset (3 Replica-like, 2 TUM)


@dataclass(frozen=True)
class DensifyConfig:
    silhouette_threshold: float = 0.5
    depth_error_factor: float = 50.0  # x median depth error


@dataclass(frozen=True)
class KeyframeConfig:
    every: int = 5
    overlap_samples: int = 1600


@dataclass(frozen=True)
class LossConfig:
    color_weight: float = 0.5
    depth_weight: float = 1.0


@dataclass(frozen=True)
class GaussianConfig:
    kind: GaussianKind = "3d"
    isotropic: bool = True


@dataclass(frozen=True)
class RenderConfig:
    backend: RenderBackend = "auto"
    packed: bool = False
    eps2d: float = 0.3
    near: float = 0.01
    far: float = 100.0


@dataclass(frozen=True)
class RunConfig:
    output: str = "outputs"
    name: str = ""  # empty: derived from the dataset and preset
    device: str = "auto"  # auto | cpu | cuda
    eval_every: int = 5  # render metrics on every Nth frame
    loader: LoaderKind = "pipelined"
    compile: Switch = "auto"  # torch.compile the per-iteration loss and pose functions (auto: on CUDA)
    queue_size: int = 4
    seed: int = 0
    save_every_s: float = 60.0  # map, trajectory and checkpoint written this often while running (and at the end)


PoseUse = Literal["initial_guess", "groundtruth", "ignore"]


@dataclass(frozen=True)
class LiveConfig:
    """The `serve` daemon and its live sources."""

    width: int = 0  # SLAM's working size; 0: the first frame's (later frames are resized to it)
    height: int = 0
    save_every_s: float = 60.0  # map, trajectory and checkpoint written this often (and at exit)
    status_host: str = "127.0.0.1"
    status_port: int = 8765  # JSON status at http://status_host:status_port/status; 0: off
    retry_initial_s: float = 1.0  # back-off after a failed connection, doubling up to retry_max_s
    retry_max_s: float = 30.0
    connect_timeout_s: float = 10.0  # signalling to first frame
    stall_timeout_s: float = 5.0  # no frame for this long: the phone is gone, reconnect
    device_pose: PoseUse = "initial_guess"  # NeRFCapture: what the phone's pose is used for
    dds_domain: int = 0  # NeRFCapture: the DDS domain id (the app uses 0)


@dataclass(frozen=True)
class ViewerConfig:
    enabled: bool = False
    host: str = "127.0.0.1"  # 0.0.0.0 exposes it to the network: deliberately
    port: int = 8080
    max_hz: float = 1.0  # frame snapshots (stats, images, camera) per second at most
    map_every_s: float = 5.0  # the whole map is sent this often at most (~32 bytes per Gaussian; viewer.md)


@dataclass(frozen=True)
class Config:
    preset: str = "base"
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    gaussians: GaussianConfig = field(default_factory=GaussianConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    run: RunConfig = field(default_factory=RunConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    viewer: ViewerConfig = field(default_factory=ViewerConfig)


# tracking iters / mapping iters / mapping window / keyframe every
PRESETS: dict[str, tuple[int, int, int, int]] = {
    "base": (40, 60, 24, 5),
    "small": (10, 15, 15, 5),
    "tiny": (4, 6, 6, 5),
    "tum": (200, 30, 20, 5),
}

# Values that SplaTAM tunes per dataset family.
DATASET_DEFAULTS: dict[str, dict[str, float]] = {
    "replica": {"tracking.lr_rotation": 0.0004, "mapping.scene_radius_divisor": 3.0},
    "tum": {"tracking.lr_rotation": 0.002, "mapping.scene_radius_divisor": 2.0},
}
