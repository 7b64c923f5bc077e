"""The configuration schema: one frozen dataclass per component, the presets and the values
SplaTAM tunes per dataset family. Loading, overriding and writing live in `loading.py`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from pipeline.errors import UserError

DatasetFormat = Literal["auto", "replica", "tum", "rosbag"]
GaussianKind = Literal["3d", "2d"]
RenderBackend = Literal["auto", "gsplat", "reference"]
LoaderKind = Literal["pipelined", "sync"]
Switch = Literal["auto", "on", "off"]
MapOptimizerKind = Literal["adam", "selective_adam"]
MappingRate = Literal["auto", "frame", "keyframe"]
Schedule = Literal["sequential", "process", "thread"]
TrackingMethod = Literal["adam", "align"]
OdometryKind = Literal["features", "off"]
ViewerKind = Literal["viser", "open3d", "rerun"]
ColorEncoding = Literal["bt709_full", "bt601_limited"]  # a YUV stream's matrix and range
PoseUse = Literal["initial_guess", "groundtruth", "ignore"]  # what a source's own poses are used for


def switched_on(switch: Switch, cuda: bool) -> bool:
    """A Switch setting: on, off, or auto (on with CUDA)."""
    return switch == "on" or (switch == "auto" and cuda)


def keyframe_rate(rate: MappingRate, schedule: Schedule) -> bool:
    """Whether only keyframes are mapped (`mapping.rate`; auto: under the process and thread
    schedules only, so that `sequential` stays SplaTAM's order unless asked)."""
    return rate == "keyframe" or (rate == "auto" and schedule != "sequential")


@dataclass(frozen=True)
class DatasetConfig:
    """The input sequence on disk and how much of it is used."""

    path: str = ""  # dataset folder (Replica or TUM layout) or bag (ROS 1 .bag, RealSense .bag, ROS 2 folder, .db3, .mcap); empty: generate the embedded synthetic room
    path_as_given: str = ""  # the folder as the command line named it (a run records it; path is made absolute)
    format: DatasetFormat = "auto"  # layout of the folder; auto: detected from its files (a bag: rosbag)
    width: int = 0  # working width in pixels; 0: native size, else resized (colour linear, depth nearest)
    height: int = 0  # working height in pixels (set with width)
    start: int = 0  # first frame used
    end: int = -1  # frame after the last one used (exclusive); -1: to the end
    stride: int = 1  # use every Nth frame
    intrinsics: tuple[float, ...] = ()  # fx, fy, cx, cy in pixels at the stored size; empty: from the layout
    depth_scale: float = 0.0  # depth image units per metre; 0: by layout (TUM 5000, Replica 6553.5); millimetres: 1000
    depth_range_m: tuple[float, ...] = (0.1, 20.0)  # first frames' median depth outside: the run stops; (): no check
    color_topic: str = ""  # a bag's colour images (sensor_msgs/Image or CompressedImage); empty: the only one
    depth_topic: str = ""  # a bag's depth images (16UC1 millimetres, 32FC1 metres); empty: the only one
    camera_info_topic: str = ""  # a bag's sensor_msgs/CameraInfo; empty: the colour topic's, or the only one
    pose_topic: str = ""  # a bag's poses (PoseStamped, PoseWithCovarianceStamped, Odometry; /tf: set pose_frames); empty: the only one, if any
    pose_frames: tuple[str, ...] = ()  # /tf's world and camera frames, e.g. map,camera_optical; empty: no /tf pose
    pose_use: PoseUse = "groundtruth"  # a bag's poses: the reference for the ATE, tracking's starting guess, or ignored


# The embedded default scene (width, height, frames): full Replica size on a GPU, a small one a
# 2-core CPU finishes in minutes.
SYNTHETIC_GPU = (1200, 680, 200)
SYNTHETIC_CPU = (128, 96, 20)


@dataclass(frozen=True)
class SyntheticConfig:
    """The embedded default scene; sizes of 0 are chosen by device (small on the CPU)."""

    frames: int = 0  # frames generated; 0: by device (200 with CUDA, 20 on the CPU)
    width: int = 0  # pixels; 0: by device (1200 with CUDA, 128 on the CPU)
    height: int = 0  # pixels; 0: by device (680 with CUDA, 96 on the CPU)
    seed: int = 0  # chooses the room's objects, textures and the camera path
    speed: float = 0.3  # metres per second along the path
    jitter: float = 0.01  # metres (and radians x 0.5) of hand-held shake
    fps: float = 30.0  # frame rate of the timestamps
    layout: DatasetFormat = "replica"  # folder layout written: replica or tum
    depth_noise: float = 0.0  # TUM layout only: depth noise std = depth_noise x depth^2, metres
    holes: float = 0.0  # TUM layout only: fraction of depth pixels zeroed, in blobs
    time_jitter: float = 0.0  # TUM layout only: depth and pose timestamp offsets up to this, seconds
    loops: int = 0  # a closed path round the room, this many times (0: the open path); frames 0: all of it
    trap: bool = False  # the room's halves are twins (turned by 180 degrees): look-alike places, not a loop


@dataclass(frozen=True)
class TrackingConfig:
    """Camera tracking: the pose estimated against the map, per frame."""

    method: TrackingMethod = "adam"  # adam: SplaTAM's rendering loss; align: dense RGB-D alignment to one render
    iters: int = 40  # adam's optimisation iterations per frame (the preset sets it)
    lr_rotation: float = 0.0  # Adam step of the pose rotation; 0: by dataset (0.0004 Replica-like, 0.002 TUM)
    lr_translation: float = 0.002  # Adam step of the pose translation, metres
    silhouette_threshold: float = 0.99  # only pixels the map covers at least this much count in the loss
    lost_translation_m: float = 0.3  # a jump beyond this from the guess, per usual frame interval since the last good frame, marks tracking lost
    lost_coverage: float = 0.05  # fewer pixels than this fraction above the threshold marks it lost
    relocalise_candidates: int = 3  # keyframe poses a lost frame is tracked again from (0: no relocalisation)
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
    align_recovery_iters: int = 30  # align: coarsest-level iterations of the recovery attempt (wide schedule)
    align_wide_iters: tuple[int, ...] = (20, 10, 6, 4)  # align: a large step's solve per level (a level more)
    align_large_step_m: float = 0.03  # align: a solve moving the camera further renders again there, solves wide
    align_grid_m: float = 0.15  # align: a frame expected far from its prediction is solved from it and from the camera moved this far sideways and along its axis (3 x 3); the start of least residual at the coarse levels goes on to the finest (0: the prediction alone)
    align_large_step_deg: float = 2.0  # align: likewise for its rotation, degrees
    align_max_renders: int = 3  # align: renders per frame at most (1: one render, no realignment)
    align_graph: Switch = "auto"  # align: replay each solve as a recorded CUDA graph (auto: on CUDA)
    align_fixed_capacity: Switch = "auto"  # align: render the map at a fixed intersection capacity, with no host read of the count (auto: on CUDA; 3D Gaussians, unpacked)
    odometry: OdometryKind = "off"  # features: a second guess from image features matched to the frame before (visual odometry), tracked too where it and constant velocity disagree; off: constant velocity only (the default: on slow motion odometry gains nothing and costs 11-20% of the frames/s; turn it on for fast hand-held motion)
    odometry_features: int = 1000  # ORB keypoints per frame at most
    odometry_min_inliers: int = 15  # feature matches agreeing in the image and in depth for a motion to count
    odometry_agree_m: float = 0.03  # guesses this close (and odometry_agree_deg) are tracked once, from odometry's
    odometry_agree_deg: float = 2.0  # likewise for their rotation, degrees


@dataclass(frozen=True)
class MappingConfig:
    """Mapping: the Gaussians optimised over a window of keyframes, per frame."""

    iters: int = 60  # optimisation iterations per frame (the preset sets it)
    window: int = 24  # keyframes mapped with each frame, the current one included (the preset sets it)
    lr_means: float = 1e-4  # Adam step of the Gaussian centres, metres
    lr_colors: float = 2.5e-3  # Adam step of the colours
    lr_rotations: float = 1e-3  # Adam step of the rotations (quaternions)
    lr_opacities: float = 5e-2  # Adam step of the opacity logits
    lr_scales: float = 1e-3  # Adam step of the log-scales
    ssim_weight: float = 0.2  # weight of 1 - SSIM in the colour loss (the rest is L1)
    prune_opacity: float = 0.005  # Gaussians below this opacity are removed at the prune iterations
    prune_scale_factor: float = 0.1  # Gaussians larger than this x scene radius are removed
    prune_at: tuple[int, ...] = (0, 20)  # mapping iterations at which pruning runs
    scene_radius_divisor: float = 0.0  # scene radius = first frame's max depth / this; 0: by dataset (3 Replica, 2 TUM)
    max_gaussians: int = 0  # the map's bound (0: none); past it the least opaque go, down to 90% of it
    views_per_step: int = 1  # keyframe views rendered together per optimiser step (the same renders in all)
    optimizer: MapOptimizerKind = "adam"  # selective_adam: only the Gaussians the step's views saw are updated
    rate: MappingRate = "auto"  # keyframe: only keyframes are densified and mapped (chosen on the tracking side by what they add), the rest tracked only; frame: every frame mapped; auto: keyframe under the process schedule, frame under sequential (SplaTAM's order)
    refine_while_idle: bool = True  # process schedule: while no frame waits, refinement passes over the keyframes (in turn the newest one's covisible window and the next of all of them)
    refine_between: int = 0  # sequential schedule at rate=keyframe: view renders of refinement over the keyframes after each frame between keyframes (0: none; one costs 12-14 ms a frame on an H200)
    refine_pose_lr: float = 1e-4  # refinement passes move the keyframes' poses too (Adam step of a twist; 0: fixed)
    final_iters: int = 0  # an offline run ends with this many view renders of refinement over all keyframes
    final_pose_lr: float = 1e-4  # the final refinement moves the keyframes' poses too (Adam step of a twist; 0: fixed): a global adjustment at 2e-3 (bench/NOTES.md)
    adjust_window: int = 0  # at each keyframe kept, it and the keyframes that see most of it (this many in all) are adjusted: their poses with the map (0: off)
    adjust_iters: int = 200  # an adjustment's view renders at most
    adjust_pose_lr: float = 2e-3  # Adam step of an adjusted keyframe's twist (radians, metres)
    adjust_converged: float = 5e-4  # an adjustment stops once a round of renders moved no twist component further
    graph: Switch = "auto"  # passes at fixed poses with adam: Gaussians and tile intersections at a fixed capacity, each step replayed as a CUDA graph (auto: on CUDA; on the CPU the same steps, ungraphed)


@dataclass(frozen=True)
class DensifyConfig:
    """Where new Gaussians are added from each tracked frame."""

    silhouette_threshold: float = 0.5  # pixels the map covers less than this get new Gaussians
    depth_error_factor: float = 50.0  # so do pixels whose depth error exceeds this x the median error


@dataclass(frozen=True)
class KeyframeConfig:
    """Which frames are kept for mapping."""

    every: int = 5  # every Nth frame becomes a keyframe (the last frame too); mapping.rate=keyframe: the longest gap between keyframes
    overlap_samples: int = 1600  # pixels sampled to measure a keyframe's overlap with the current frame
    min_overlap: float = 0.9  # mapping.rate=keyframe: a frame with less than this fraction of its valid pixels inside the last keyframe's view is a keyframe
    max_translation: float = 0.08  # mapping.rate=keyframe: so is one whose camera moved more than this x its median depth from the last keyframe (MonoGS's kf_translation)
    min_coverage: float = 0.5  # mapping.rate=keyframe: so is one the map covers less of (tracking's coverage, against a map holding every keyframe so far)
    max_kept: int = 0  # keyframes held at most (0: all); past it the most redundant viewpoint goes


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure: a keyframe that sees again what an old one saw, verified by dense alignment,
    and the keyframe pose graph optimised (the 'loops' extra: GTSAM)."""

    enabled: bool = False  # close loops (needs the 'loops' extra: GTSAM)
    min_keyframes_back: int = 10  # a candidate is at least this many keyframes older than the current one
    radius_m: float = 0.5  # a candidate's camera centre lies within this of the current one (current estimates)
    max_angle_deg: float = 60.0  # and its viewing direction within this angle
    min_overlap: float = 0.3  # and this fraction of the current keyframe's pixels lands in its image (overlap samples)
    min_similarity: float = 0.5  # and the descriptors' correlation (-1 to 1) is at least this
    appearance_similarity: float = 0.8  # beyond the estimates' reach (radius, angle, overlap), a candidate by its look alone: this correlation at least (the cabinet's real revisit: 0.86-0.93) ...
    drift_fraction: float = 0.3  # ... and its camera centre within radius_m + this x the path travelled since it (as far as the estimates may have drifted)
    appearance_offset_m: float = 0.2  # such a candidate is verified from the identity and from the camera moved this far sideways and along its axis (a 3 x 3 grid), the best at the coarse levels goes on to the finest
    max_candidates: int = 3  # candidates verified per keyframe, most similar first
    verify_iters: tuple[int, ...] = (30, 10, 5)  # verification: alignment iterations per pyramid level, coarse to fine
    min_coverage: float = 0.3  # verified: inliers / valid-depth pixels of the current keyframe at least this
    min_inliers: float = 0.7  # verified: of the pixels on the candidate's valid depth, this fraction within the gate
    max_residual_m: float = 0.015  # verified: RMS point-to-plane residual at most this
    max_intensity_rms: float = 0.25  # verified: RMS intensity residual (less its mean) at most this
    min_conditioning: float = 1e-3  # verified: eigenvalue ratio of the scaled normal equations at least this
    agree_m: float = 0.08  # accepted: two verified loops place the current keyframe within this of each other
    agree_deg: float = 4.0  # and within this angle
    confirm_keyframes: int = 2  # the second loop may be one of this many keyframes before (0: a candidate only)
    information_scale: float = 0.01  # an alignment's normal equations x this: an edge's information (pixels correlate)
    odometry_sigma_m: float = 0.2  # an odometry edge whose alignment judged the estimates' step unsound (tracked wrong, as on fast motion): std, metres; soft, so a loop's correction goes there
    odometry_sigma_deg: float = 10.0  # and of its rotation, degrees
    loop_kernel_width: float = 3.0  # Cauchy kernel on loop edges, in standard deviations
    max_loop_residual_m: float = 0.05  # a loop edge the optimised graph misses by more is dropped
    max_loop_residual_deg: float = 3.0  # likewise in rotation
    max_iterations: int = 100  # Levenberg-Marquardt iterations of the pose graph at most


@dataclass(frozen=True)
class LossConfig:
    """Weights of the rendering losses."""

    color_weight: float = 0.5  # weight of the colour term in tracking and mapping losses
    depth_weight: float = 1.0  # weight of the depth (L1, metres) term


@dataclass(frozen=True)
class GaussianConfig:
    """The kind of Gaussian the map is made of."""

    kind: GaussianKind = "3d"  # 3d Gaussians, or 2d (flat discs, surfels)
    isotropic: bool = True  # one scale per Gaussian (SplaTAM) instead of three
    seed_scale: float = 1.0  # a new Gaussian's scale in footprints of its pixel (depth / focal length; SplaTAM: 1)
    seed_opacity: float = 0.5  # a new Gaussian's opacity (SplaTAM: 0.5)


@dataclass(frozen=True)
class RenderConfig:
    """The differentiable renderer."""

    backend: RenderBackend = "auto"  # gsplat (CUDA) or the pure-PyTorch reference; auto: gsplat on a GPU
    packed: bool = False  # gsplat's packed mode (less memory, usually slower)
    eps2d: float = 0.3  # pixels^2 added to every projected covariance (anti-aliasing floor)
    near: float = 0.01  # near plane, metres
    far: float = 100.0  # far plane, metres


@dataclass(frozen=True)
class SlamConfig:
    """How tracking and mapping share the frames."""

    schedule: Schedule = "sequential"  # sequential: one frame at a time; process: mapping in a process of its own; thread: the same in a thread of this process (no second start-up; the GIL shared)
    max_lead: int = 2  # process, offline: frames tracking may run ahead of mapping (mapping.rate=keyframe: keyframes; live: no bound)
    backend_timeout_s: float = 120.0  # process: mapping silent this long is hung (first compile ~1 min)

    def __post_init__(self) -> None:
        if not self.backend_timeout_s > 0:  # 0 would take a healthy mapping process for a hung one at once
            raise UserError(f"slam.backend_timeout_s must be > 0 (seconds), not {self.backend_timeout_s}")


@dataclass(frozen=True)
class RunConfig:
    """The run itself: outputs, device, evaluation, the pipeline."""

    output: str = "outputs"  # where run folders go
    name: str = ""  # run folder name; empty: derived from the dataset and preset
    device: str = "auto"  # auto | cpu | cuda (auto: cuda when available)
    eval_every: int = 5  # render metrics on every Nth frame
    loader: LoaderKind = "pipelined"  # asyncio pipeline, or sync: read, decode and process one frame at a time
    compile: Switch = "auto"  # torch.compile the per-iteration loss and pose functions (auto: on CUDA)
    compile_grid: bool = True  # with compile: the align grid's nine-start iteration compiled too (false: replayed uncompiled in its CUDA graph; its compiles were 6.5 of a warm start's 11 s on the CPU)
    precompile: bool = False  # with compile: the align iterations built once as AOTInductor packages (the cache folder) and loaded without tracing in later runs
    queue_size: int = 4  # frames each pipeline queue holds
    seed: int = 0  # seeds mapping's keyframe picks and pixel sampling
    save_every_s: float = 60.0  # map, trajectory and checkpoint written this often while running (and at the end)
    renders: int = 20  # evaluated frames whose render is saved beside the input in renders/ (evenly spread; 0: none)
    kernel_sample: Switch = "auto"  # the GPU's kernel busy fraction over frames 10-60 (CUPTI; auto: on CUDA)


@dataclass(frozen=True)
class LiveConfig:
    """The `serve` daemon and its live sources."""

    width: int = 0  # SLAM's working size; 0: the first frame's (later frames are resized to it)
    height: int = 0  # SLAM's working height (set with width)
    save_every_s: float = 60.0  # map, trajectory and checkpoint written this often (and at exit)
    status_host: str = "127.0.0.1"  # address of the JSON status endpoint
    status_port: int = 8765  # JSON status at http://status_host:status_port/status; 0: off
    retry_initial_s: float = 1.0  # back-off after a failed connection, doubling up to retry_max_s
    retry_max_s: float = 30.0  # longest back-off between reconnection attempts
    busy_probe_s: float = 1.0  # a busy phone (HTTP 403) is asked again this often, without back-off
    connect_timeout_s: float = 10.0  # signalling to first frame
    http_timeout_s: float = 5.0  # Record3D: an HTTP reply of the phone slower than this is "no reply"
    stall_timeout_s: float = 10.0  # no frame for this long: the phone is gone, reconnect
    vp8_color: ColorEncoding = "bt709_full"  # Record3D: how VP8 frames (which signal no matrix) are decoded
    device_pose: PoseUse = "initial_guess"  # NeRFCapture: what the phone's pose is used for
    dds_domain: int = 0  # NeRFCapture: the DDS domain id (the app uses 0)
    max_keyframes: int = 200  # a live session's keyframes.max_kept unless that is set: memory flat for hours
    max_gaussians: int = 2_000_000  # a live session's mapping.max_gaussians unless that is set
    record: bool = False  # save the frames SLAM receives in <run folder>/recording (TUM layout), to re-run offline
    warm_up: Switch = "auto"  # compile and record SLAM's kernels on the first frame, then drop it (auto: on CUDA)


@dataclass(frozen=True)
class ViewerConfig:
    """The live viewer of `--viewer`."""

    enabled: bool = False  # show the run in a viewer (--viewer)
    kind: ViewerKind = "viser"  # viser: a web page; open3d: a desktop window (the mesh extra); rerun: rerun's viewer
    host: str = "127.0.0.1"  # web viewer address; 0.0.0.0 exposes it to the network: deliberately
    port: int = 8080  # web viewer port
    max_hz: float = 1.0  # frame snapshots (stats, images, camera) per second at most; rerun logs every frame
    map_every_s: float = 5.0  # the whole map is sent this often at most (~32 bytes per Gaussian; viewer.md)
    rerun_save: str = ""  # kind rerun: write the recording to this .rrd file instead of spawning rerun's viewer


@dataclass(frozen=True)
class Config:
    """Every setting of a run; `gsplatam config` lists them."""

    preset: str = "base"  # tiny, small, base or tum: tracking and mapping iterations, window, keyframe rate
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    slam: SlamConfig = field(default_factory=SlamConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loops: LoopConfig = field(default_factory=LoopConfig)
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
    "replica": {"tracking.lr_rotation": 0.0004, "mapping.scene_radius_divisor": 3.0, "dataset.depth_scale": 6553.5},
    "tum": {"tracking.lr_rotation": 0.002, "mapping.scene_radius_divisor": 2.0, "dataset.depth_scale": 5000.0},
}
# a bag is a real depth sensor's, as TUM's; its depth comes in its messages' own units
DATASET_DEFAULTS["rosbag"] = {k: v for k, v in DATASET_DEFAULTS["tum"].items() if k != "dataset.depth_scale"}

# The preset of a run on the CPU (and of live input) where none is named.
DEFAULT_PRESET_CPU = "tiny"
