"""What a benchmark matrix is made of, its variants and its generated sequences, apart from
the harness (bench.py) so that `gsplatam bench --help` lists them without loading torch."""

from __future__ import annotations

SMALL_SEEDS = ("gaussians.seed_scale=0.35", "gaussians.seed_opacity=0.99", "render.eps2d=0.1")  # Change 40

# Side-by-side switches, compared in one invocation (the table's ratios: to the first variant given).
ABLATIONS: dict[str, tuple[str, ...]] = {
    "default": (),
    "sync-loader": ("run.loader=sync",),
    "no-compile": ("run.compile=off",),
    "packed": ("render.packed=true",),
    "3d-anisotropic": ("gaussians.isotropic=false",),
    "2d-isotropic": ("gaussians.kind=2d",),
    "2d-anisotropic": ("gaussians.kind=2d", "gaussians.isotropic=false"),
    "sequential": ("slam.schedule=sequential",),
    "views2": ("mapping.views_per_step=2",),
    "views3": ("mapping.views_per_step=3",),
    "selective-adam": ("mapping.optimizer=selective_adam",),
    "adam": ("tracking.method=adam",),  # SplaTAM's tracker, whatever the preset's default
    "align": ("tracking.method=align",),  # dense RGB-D alignment to one render
    "align-refine": ("tracking.method=align", "tracking.refine_iters=2"),  # then 2 of adam's iterations
    "process": ("slam.schedule=process",),  # mapping in its own process, refining between frames
    "thread": ("slam.schedule=thread",),  # the process schedule's mapping side in a thread: no second start-up
    "thread-odometry-loops": ("slam.schedule=thread", "tracking.odometry=features", "loops.enabled=true"),
    "process-keyframe": ("slam.schedule=process", "mapping.rate=keyframe"),  # keyframes only densified and mapped
    "process-frame": ("slam.schedule=process", "mapping.rate=frame"),  # every frame mapped (the rate before keyframe)
    "process-views2": ("slam.schedule=process", "mapping.views_per_step=2"),
    "process-lead1": ("slam.schedule=process", "slam.max_lead=1"),
    "process-no-refine": ("slam.schedule=process", "mapping.refine_while_idle=false"),
    "process-fixed-poses": ("slam.schedule=process", "mapping.refine_pose_lr=0"),
    "final-iters": ("mapping.final_iters=600",),  # then 600 view renders over every keyframe
    "process-final": ("slam.schedule=process", "mapping.final_iters=600"),
    "process-no-sample": ("slam.schedule=process", "run.kernel_sample=off"),  # the kernel sampler's own cost
    "loops": ("loops.enabled=true",),  # loop closure on the keyframe pose graph
    "process-loops": ("slam.schedule=process", "loops.enabled=true"),
    "process-one-render": (  # align before large steps were followed: one render, no wide schedule
        "slam.schedule=process", "tracking.align_max_renders=1", "tracking.align_wide_iters=10,6,4",
    ),
    "process-adjust": ("slam.schedule=process", "mapping.adjust_window=5"),  # local bundle adjustment at each keyframe
    "process-adjust-loops": ("slam.schedule=process", "mapping.adjust_window=5", "loops.enabled=true"),
    "process-odometry": ("slam.schedule=process", "tracking.odometry=features"),  # visual odometry's second guess
    "sequential-keyframe": ("slam.schedule=sequential", "mapping.rate=keyframe"),  # one thread, keyframes only mapped
    "sequential-keyframe-no-compile": ("slam.schedule=sequential", "mapping.rate=keyframe", "run.compile=off"),
    "sequential-keyframe-grid-eager": ("slam.schedule=sequential", "mapping.rate=keyframe", "run.compile_grid=false"),
    "sequential-odometry-grid-eager": ("slam.schedule=sequential", "tracking.odometry=features", "run.compile_grid=false"),
    "process-grid-eager": ("slam.schedule=process", "run.compile_grid=false"),  # the grid's iteration uncompiled
    "sequential-keyframe-precompiled": ("slam.schedule=sequential", "mapping.rate=keyframe", "run.precompile=true"),
    "process-precompiled": ("slam.schedule=process", "run.precompile=true"),  # align iterations as AOTInductor packages
    "sequential-odometry-precompiled": ("slam.schedule=sequential", "tracking.odometry=features", "run.precompile=true"),
    "sequential-keyframe-refine": ("slam.schedule=sequential", "mapping.rate=keyframe", "mapping.refine_between=1"),
    "process-no-compile": ("slam.schedule=process", "run.compile=off"),  # graphs of eager kernels: no dynamo at start
    "process-eager-render": ("slam.schedule=process", "tracking.align_fixed_capacity=off"),  # gsplat's own tracking render
    "process-odometry-loops": ("slam.schedule=process", "tracking.odometry=features", "loops.enabled=true"),
    "sequential-odometry": ("slam.schedule=sequential", "tracking.odometry=features"),
    "sequential-odometry-small-seeds": (  # Change 40: smaller, nearly opaque seeds, a lower anti-aliasing floor
        "slam.schedule=sequential", "tracking.odometry=features", *SMALL_SEEDS,
    ),
    "process-small-seeds": ("slam.schedule=process", *SMALL_SEEDS),
    "sequential-odometry-loops": ("slam.schedule=sequential", "tracking.odometry=features", "loops.enabled=true"),
    "sequential-odometry-adjust": ("slam.schedule=sequential", "tracking.odometry=features", "mapping.adjust_window=5"),
    "sequential-odometry-global": (  # then a global adjustment: every keyframe's pose with the map
        "slam.schedule=sequential", "tracking.odometry=features", "mapping.final_iters=1000", "mapping.final_pose_lr=2e-3",
    ),
    "sequential-odometry-adjust-loops": (
        "slam.schedule=sequential", "tracking.odometry=features", "mapping.adjust_window=5", "loops.enabled=true",
    ),
}  # fmt: skip


# Generated sequences by name; any other sequence is a dataset folder.
SYNTHETIC_SEQUENCES: dict[str, tuple[str, ...]] = {
    "synthetic": (),  # the Replica-like room, 1200x680 on a GPU
    "synthetic-640x480": ("synthetic.width=640", "synthetic.height=480"),  # the same room at the TUM size
    "synthetic-fast": ("synthetic.speed=1.0",),  # the same room, the camera 3.3x faster (1 m/s)
    "synthetic-tum": (  # TUM-like: 640x480, Kinect-like depth noise and holes, timestamp jitter
        "synthetic.layout=tum", "synthetic.width=640", "synthetic.height=480",
        "synthetic.depth_noise=0.0015", "synthetic.holes=0.02", "synthetic.time_jitter=0.004",
    ),
    "synthetic-loops": (  # TUM-like, twice round the room at 0.75 m/s: a long sequence that revisits places
        "synthetic.layout=tum", "synthetic.width=640", "synthetic.height=480", "synthetic.loops=2", "synthetic.speed=0.75",
        "synthetic.depth_noise=0.0015", "synthetic.holes=0.02", "synthetic.time_jitter=0.004",
    ),
    "synthetic-fast-loops": (  # TUM-like, twice round the room at 1 m/s (3.3 cm a frame): fast steps, then revisits
        "synthetic.layout=tum", "synthetic.width=640", "synthetic.height=480", "synthetic.loops=2", "synthetic.speed=1.0",
        "synthetic.depth_noise=0.0015", "synthetic.holes=0.02", "synthetic.time_jitter=0.004",
    ),
    "synthetic-trap": (  # TUM-like in the room of look-alike halves: no place is revisited
        "synthetic.layout=tum", "synthetic.width=640", "synthetic.height=480", "synthetic.trap=true", "synthetic.speed=0.75",
        "synthetic.depth_noise=0.0015", "synthetic.holes=0.02", "synthetic.time_jitter=0.004",
    ),
}  # fmt: skip


def default_variants(ablations: bool) -> list[str]:
    return list(ABLATIONS) if ablations else ["default"]
