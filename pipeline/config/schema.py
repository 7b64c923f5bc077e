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
MapOptimizerKind = Literal["adam", "selective_adam"]
TrackingMethod = Literal["adam", "align"]


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
    method: TrackingMethod = "adam"  # adam: SplaTAM's rendering loss; align: dense RGB-D alignment to one render
    iters: int = 40  # adam's iterations
    lr_rotation: float = 0.0  # 0: by dataset (0.0004 Replica-like, 0.002 TUM)
    lr_translation: float = 0.002
    silhouette_threshold: float = 0.99
    lost_translation_m: float = 0.3  # a jump beyond this from the initial guess marks tracking lost
    lost_coverage: float = 0.05  # fewer pixels than this fraction above the threshold marks it lost
    refine_iters: int = 0  # align: then this many of adam's iterations from the aligned pose
    align_iters: tuple[int, ...] = (10, 6, 4)  # align: iterations per pyramid level, coarse to fine (one level each)
    align_depth_sigma_m: float = 0.01  # align: Huber scale of the point-to-plane residual
    align_color_sigma: float = 0.05  # align: Huber scale of the intensity residual (intensity in [0, 1])
    align_photometric_weight: float = 0.1  # align: weight of the photometric term against the geometric one
    align_min_silhouette: float = 0.5  # align: render pixels of less accumulated opacity are not aligned to
    align_max_depth_diff_m: float = 0.05  # align: gate on the point-to-plane residual at full size, x2 per level
    align_min_inliers: float = 0.5  # align: fewer associated pixels within the gate than this fraction fails
    align_min_conditioning: float = 1e-4  # align: a smaller eigenvalue ratio of the scaled normal equations fails
    align_max_residual_m: float = 0.02  # align: a larger RMS point-to-plane residual fails
    align_max_intensity_rms: float = 0.2  # align: a larger RMS intensity residual (less its mean) fails
    align_recovery_iters: int = 30  # align: coarsest-level iterations of the one recovery attempt
    align_graph: Switch = "auto"  # align: replay each solve as a recorded CUDA graph (auto: on CUDA)


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
    max_gaussians: int = 0  # the map's bound (0: none); past it the least opaque go, down to 90% of it
    views_per_step: int = 1  # keyframe views rendered together per optimiser step (same renders in all)
    optimizer: MapOptimizerKind = "adam"  # selective_adam: only the Gaussians the step's views saw


@dataclass(frozen=True)
class DensifyConfig:
    silhouette_threshold: float = 0.5
    depth_error_factor: float = 50.0  # x median depth error


@dataclass(frozen=True)
class KeyframeConfig:
    every: int = 5
    overlap_samples: int = 1600
    max_kept: int = 0  # keyframes held at most (0: all); past it the most redundant viewpoint goes (keyframes.py)


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


Schedule = Literal["sequential", "overlapped"]


@dataclass(frozen=True)
class SlamConfig:
    """How tracking and mapping share the frames."""

    schedule: Schedule = "sequential"  # overlapped: tracking and mapping as two concurrent stages
    max_lead: int = 2  # overlapped, offline: frames tracking may run ahead of mapping (live: no bound)


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
    max_keyframes: int = 200  # a live session's keyframes.max_kept unless that is set: memory flat for hours
    max_gaussians: int = 2_000_000  # a live session's mapping.max_gaussians unless that is set


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
    slam: SlamConfig = field(default_factory=SlamConfig)
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

# The tracking method of each preset: the one place to flip after measuring (bench part `tracker`).
PRESET_TRACKING: dict[str, TrackingMethod] = {"base": "adam", "small": "align", "tiny": "align", "tum": "adam"}

# Values that SplaTAM tunes per dataset family.
DATASET_DEFAULTS: dict[str, dict[str, float]] = {
    "replica": {"tracking.lr_rotation": 0.0004, "mapping.scene_radius_divisor": 3.0},
    "tum": {"tracking.lr_rotation": 0.002, "mapping.scene_radius_divisor": 2.0},
}
