#!/usr/bin/env bash
# The GPU suite on a bare device machine: install the carried wheels, then run the named parts.
# Usage (from the repo root, with .device/ holding the gsplat wheel and .data/ the TUM sample and, for the drift parts, the cabinet loop):
#   PATH=.venv/bin:$PATH DRY=1 bash bench/gpu_suite.sh /tmp/dry drift-tiny: a rehearsal of parts on this machine's CPU at 64x48 (data from ../shared/data)
#   bash bench/gpu_suite.sh OUT_DIR parity schedules-tiny schedules-small schedules-base process-options ssim syncs costs tiny small base tum presets-fast presets-base presets-tum types pipeline ablations profile memory viewer tracker exports live-warmup
# The ray parts (ray-live, ray-matrix) also need Ray's wheels in .whl-ray/ (docs/cluster.md),
# and ray-live's NeRFCapture phones cyclonedds' wheel in .whl-dds/; the live parts aiortc's in .whl-live/; loops GTSAM's in .whl-loops/.
# Results go to a work folder and, when the suite ends (or is stopped), into OUT_DIR/results.tar.gz:
# one file, since a device call returns at most 8 files.
set -uo pipefail
dest=${1:?usage: gpu_suite.sh OUT_DIR PART...}
shift
out=$(mktemp -d)
mkdir -p "$dest"
trap 'tar -czf "$dest/results.tar.gz" -C "$out" .' EXIT
trap 'exit 143' TERM INT
dry=()  # DRY=1: a rehearsal on this machine's CPU before a device call (nothing installed, bench parts tiny)
if [ -n "${DRY:-}" ]; then
  dry=(--set run.device=cpu --set dataset.width=64 --set dataset.height=48 --set dataset.end=6
       --set synthetic.width=64 --set synthetic.height=48 --set synthetic.frames=6)
  export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 GSPLATAM_COMMIT=${GSPLATAM_COMMIT:-dry}
  data=${DATA:-../shared/data}
  runs=$(mktemp -d)  # run folders of its own: /tmp is shared on this machine
else
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/site .device/*.whl $(ls .whl-live/*.whl .whl-ray/*.whl .whl-dds/*.whl .whl-loops/*.whl 2>/dev/null) || exit 1
  export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 PYTHONFAULTHANDLER=1 PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True
  export XDG_CACHE_HOME=$PWD/.device/cache  # our CUDA extension built by an earlier call comes carried in .device/
  # The image's CXX (/opt/gcc/bin/g++, a wrapper of the system's GCC 13.3) links libstdc++ into shared libraries
  # statically: an AOTInductor package built with it crashes the process that loads it (bench/NOTES.md, Change 36)
  export CXX=/usr/bin/g++
  export GSPLATAM_COMMIT=${GSPLATAM_COMMIT:?set GSPLATAM_COMMIT to the commit measured, since the git of the device copy is stale}
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
  data=${DATA:-.data}
  runs=/tmp/runs
fi
tum=$data/tum_fr1_xyz_37
cabinet=$data/tum_fr3_cabinet_kf57  # issue 35's real loop (57 frames round a cabinet), carried in .data/ beside the TUM sample
bench() { python3 -m pipeline bench --quiet --out "$out" --runs "$runs" "$@" "${dry[@]}" 2>&1 | tee -a "$out/bench.log" | grep -v "^gsplatam: bench\|^gsplatam: device\|^gsplatam: dataset" | tail -n 12
  for run in "$runs"/*/; do [ -L "${run%/}" ] && continue  # each run's poses and per-frame log (kilobytes), for per-frame analysis here
    mkdir -p "$out/runs/$(basename "$run")" && cp "$run"trajectory.txt "$run"groundtruth.txt "$run"frames.csv "$run"metrics.json "$out/runs/$(basename "$run")/" 2>/dev/null
  done; }
drift_variants=process-one-render,process,process-loops,process-adjust,process-adjust-loops
run_part() {
  case $part in
    parity) python3 bench/parity.py --out "$out" 2>&1 | grep -v Warning | tail -n 20 ;;
    extension) python3 -c "import torch; from pipeline.render.intersect_kernel import intersect_kernel; print('built:', intersect_kernel(torch.device('cuda')) is not None)"
               cp -r .device/cache/gsplatam/extensions "$out/" ;;  # to carry into later calls
    gpu-tests)  # GPU_TESTS=expression: only the tests it selects (pytest -k)
               python3 -m pytest tests/gpu -o addopts="" -p no:cacheprovider -q -rs ${GPU_TESTS:+-k "$GPU_TESTS"} 2>&1 \
                 | tee "$out/gpu_tests.txt" | tail -n 30 ;;
    capture-cost) python3 bench/capture_cost.py --out "$out" 2>&1 | grep -v Warning | tail -n 12 ;;
    pace-640)  # issue 34's table: sequential (SplaTAM's reference) and process (keyframe rate) at 640x480
              bench "$tum" synthetic-tum synthetic-640x480 --presets tiny,small --variants sequential,process --stem pace_640 ;;
    pace-sequential-keyframe-tiny)  # keyframe rate in one thread, both schedules, the tracking render; 640x480
              bench "$tum" synthetic-tum synthetic-640x480 --presets tiny \
                --variants sequential,sequential-keyframe,sequential-keyframe-refine,process,process-eager-render \
                --stem pace_sequential_keyframe_tiny ;;
    pace-sequential-keyframe-small)  # the three schedules tiny's call left standing (9 cells)
              bench "$tum" synthetic-tum synthetic-640x480 --presets small \
                --variants sequential,sequential-keyframe,process --stem pace_sequential_keyframe_small ;;
    drift-odometry-loops)  # issue 35 (carry .device, .data/tum_fr3_cabinet_kf57 and .whl-loops: 56 MB)
              bench "$cabinet" --presets tiny --variants process,process-odometry,process-odometry-loops \
                --set dataset.width=640 --set dataset.height=480 --stem drift_odometry_loops_cabinet ;;
    drift-lost)  # issue 35: loops searched from lost frames too (the cabinet's revisit is lost); carry as drift-odometry-loops
              bench "$cabinet" --presets tiny \
                --variants ${LOST_VARIANTS:-process-odometry,process-odometry-loops,process-loops,sequential-odometry,sequential-odometry-loops} \
                --set dataset.width=640 --set dataset.height=480 --stem drift_lost_cabinet ;;
    loops-tiny) bench synthetic-loops synthetic-trap --presets tiny --variants default,loops --stem loops_tiny ;;
    loops-trap) bench synthetic-trap --presets tiny --variants default,loops --stem loops_trap_tiny ;;  # no loop may close
    warm-start-synthetic)  # warm-start on the generated TUM-like scene (640x480): no dataset to carry
              bench synthetic-tum --presets tiny --variants sequential-keyframe,process --repeats 2 \
                --set synthetic.frames=40 --stem warm_start_synthetic_tiny ;;
    pace-1200) bench synthetic --presets tiny,small --variants sequential,process --stem pace_1200 ;;
    pace-base) bench "$tum" --presets base --variants sequential --stem pace_base_tum ;;
    odometry-cabinet) bench "$cabinet" --presets tiny --variants process,process-odometry \
                        --set dataset.width=640 --set dataset.height=480 --stem odometry_cabinet_tiny ;;
    pace-tum) bench "$tum" --presets tiny --variants sequential,process-frame,process-keyframe --stem pace_tiny_tum ;;
    drift-adjust)  # issue 35: local bundle adjustment at each keyframe (5 covisible), with and without loops, and a global one at the end; carry as drift-odometry-loops
              bench "$cabinet" --presets tiny --repeats "${REPEATS:-1}" \
                --variants ${ADJUST_VARIANTS:-sequential-odometry,sequential-odometry-adjust,sequential-odometry-global,sequential-odometry-loops,sequential-odometry-adjust-loops} \
                --set dataset.width=640 --set dataset.height=480 --stem drift_adjust_cabinet ;;
    seeds)  # issue 35, Change 40: small seeds (0.35 footprints, opacity 0.99, eps2d 0.1) against SplaTAM's: drift on the cabinet, then pace and map at 640x480
           bench "$cabinet" --presets tiny --set dataset.width=640 --set dataset.height=480 --stem seeds_cabinet \
             --variants sequential-odometry,sequential-odometry-small-seeds,process,process-small-seeds
           bench "$tum" synthetic-tum --presets tiny --variants process,process-small-seeds --stem seeds_pace ;;
    drift-cabinet) bench "$cabinet" --presets tiny --variants process-one-render,process,process-adjust \
                     --set dataset.width=640 --set dataset.height=480 --stem drift_cabinet_tiny ;;
    graph) for g in on off; do  # graphed mapping passes against eager ones, side by side in one call
             bench "$tum" synthetic-tum --presets tiny --variants sequential,process --set synthetic.frames=100 \
               --set mapping.graph=$g --stem graph_$g
           done ;;
    presets-fast) bench synthetic synthetic-tum "$tum" --presets tiny,small --stem presets_fast ;;
    presets-base) bench synthetic --presets base --stem presets_base_synthetic
                  bench "$tum" --presets base,tum --stem presets_slow_tum ;;
    presets-tum) bench synthetic synthetic-tum --presets tum --stem presets_tum_synthetic ;;
    memory) bench synthetic --presets tiny --set synthetic.frames=2000 --stem memory_2000 ;;
    types) bench synthetic "$tum" --presets tiny --variants default,3d-anisotropic,2d-isotropic,2d-anisotropic --stem gaussian_types ;;
    pipeline) bench synthetic --presets tiny --variants default,sync-loader --stem pipeline ;;
    ablations) bench synthetic --presets tiny --variants default,no-compile,sync-loader,packed --stem ablations ;;
    profile) for loader in pipelined sync; do  # 60 frames: the profiler slows every step
               python3 -m pipeline run --preset tiny --profile --quiet --output /tmp/profile --name $loader \
                 --set synthetic.frames=60 --loader $loader 2>&1 | tail -n 3
               cp /tmp/profile/$loader/profile.txt "$out/profile_tiny_$loader.txt"
               cp /tmp/profile/$loader/metrics.json "$out/profile_tiny_$loader.json"
             done ;;
    diagnose)  # issue 34: where sequential's tracking time goes (recompiles, graph breaks, per-frame times, the profile)
              for sched in sequential process; do
                TORCH_LOGS=recompiles,graph_breaks python3 -m pipeline run "$tum" --preset tiny --quiet --output /tmp/diag \
                  --name $sched --overwrite --profile --set slam.schedule=$sched "${dry[@]}" > "$out/diagnose_$sched.log" 2>&1
                tail -n 3 "$out/diagnose_$sched.log"; grep -c "Recompiling\|recompil" "$out/diagnose_$sched.log"
                for f in frames.csv metrics.json profile.txt; do cp /tmp/diag/$sched/$f "$out/diagnose_${sched}_$f" 2>/dev/null; done
              done ;;
    syncs) python3 bench/sync_points.py --out "$out" --preset tiny --frames 30 2>&1 | grep -v Warning | tail -n 40 ;;
    syncs-process)  # issue 34: the host waits left in tracking at keyframe rate (the tracking process's; 640x480)
              python3 bench/sync_points.py --out "$out" --preset tiny --frames 60 --stem sync_points_tiny_process \
                --set slam.schedule=process --set synthetic.width=640 --set synthetic.height=480 2>&1 | grep -v Warning | tail -n 25 ;;
    costs) python3 bench/iteration_costs.py --out "$out" 2>&1 | grep -v "^gsplatam" | tail -n 45 ;;
    tracker) bench synthetic synthetic-fast synthetic-tum "$tum" --presets tiny,small --variants adam,align,align-refine --stem tracker
             bench synthetic synthetic-fast synthetic-tum "$tum" --presets base --variants adam --stem tracker_base
             python3 bench/align_cost.py --out "$out" 2>&1 | grep -v Warning | tail -n 20 ;;
    tracker-tiny) bench synthetic synthetic-fast synthetic-tum "$tum" --presets tiny --set synthetic.frames=100 \
                    --variants adam,align,process --stem tracker_tiny ;;
    tracker-small) bench synthetic synthetic-fast synthetic-tum "$tum" --presets small --set synthetic.frames=100 \
                     --variants adam,align,process --stem tracker_small ;;
    tracker-base) bench synthetic synthetic-fast synthetic-tum "$tum" --presets base --set synthetic.frames=100 \
                    --variants adam --stem tracker_base ;;
    align-cost) python3 bench/align_cost.py --out "$out" 2>&1 | grep -v Warning | tail -n 20 ;;
    spread) bench synthetic --presets tiny --set synthetic.frames=100 --variants adam,process --repeats 3 --stem spread_tiny ;;
    live-age) for size in 256x192 640x480; do python3 bench/live_latency.py --out "$out" --size $size --seconds 60 2>&1 | tail -n 4; done ;;
    live-warmup) for w in off on; do  # an empty compile cache per run: the first steps as on a fresh machine
                   TORCHINDUCTOR_CACHE_DIR=$(mktemp -d) python3 bench/live_latency.py --out "$out/live_warmup_$w" \
                     --size 256x192 --seconds 60 --set live.warm_up=$w 2>&1 | tail -n 4
                 done
                 python3 bench/live_latency.py --out "$out/live_reconnect" --size 256x192 --seconds 60 \
                   --disconnect-at 25 --set live.retry_initial_s=3 2>&1 | tail -n 4 ;;
    live-process) for schedule in process sequential sequential-keyframe; do  # after a bench part: the compile cache is warm
                    rate=auto; [ "$schedule" = sequential-keyframe ] && rate=keyframe
                    timeout 200 python3 bench/live_latency.py --out "$out/$schedule" --size 640x480 --seconds ${LIVE_S:-90} \
                      --set slam.schedule=${schedule%-keyframe} --set mapping.rate=$rate 2>&1 | tail -n 3
                  done ;;
    drift-tiny|drift-small)  # issue 35: large steps, local adjustment, loops on and off; the cabinet's loop, the TUM sample, fast loops
                # (one render is align before large steps were followed; the rest the new tracking; 640x480 throughout)
                bench "$cabinet" "$tum" synthetic-fast-loops --presets "${part#drift-}" --variants $drift_variants \
                  --set dataset.width=640 --set dataset.height=480 --stem "drift_${part#drift-}" ;;
    odometry)  # issue 35: visual odometry's second guess against constant velocity's alone; every schedule it changes
              bench "$cabinet" "$tum" synthetic-fast-loops --presets tiny \
                --variants process,process-odometry,sequential,sequential-odometry \
                --set dataset.width=640 --set dataset.height=480 --stem odometry_tiny ;;
    warm-start)  # each cell a fresh process: repeat 0 on cold compile caches, repeat 1 on the warm machine a user's second run meets
              bench "$tum" --presets tiny --variants sequential-keyframe,process --repeats 2 --stem warm_start_tiny ;;
    warm-start-compile)  # issue 34: what torch.compile costs at the start and buys once steady, under CUDA graphs (no dataset to carry)
              bench synthetic-tum --presets tiny --repeats 2 --set synthetic.frames=40 --stem warm_start_compile_tiny \
                --variants sequential-keyframe,sequential-keyframe-no-compile,process,process-no-compile ;;
    warm-start-thread)  # issue 34: the thread schedule's start against the process schedule's and one thread's (no dataset)
              bench synthetic-tum --presets tiny --repeats 2 --set synthetic.frames=40 --stem warm_start_thread_tiny \
                --variants sequential-keyframe,process,thread ;;
    thread-smoke)  # the thread schedule's captures beside tracking's, uncompiled (no compile time: a short call)
              python3 -m pipeline run --preset tiny --quiet --output /tmp/smoke --name thread --overwrite \
                --set slam.schedule=thread --set run.compile=off --set synthetic.width=320 --set synthetic.height=240 \
                --set synthetic.frames=40 2>&1 | tail -n 4
              python3 -c "import json; m = json.load(open('/tmp/smoke/thread/metrics.json')); print({k: m.get(k) for k in ('schedule', 'frames', 'fps', 'stopped')}, m['ate']['rmse_cm'], m['mapping_process']['frames_mapped'])" \
                | tee "$out/thread_smoke.txt" ;;
    warm-start-grid)  # issue 34: the grid's batched iteration compiled or not: a warm start's compiles against large steps' tracking
              bench synthetic-tum --presets tiny --repeats 2 --set synthetic.frames=40 --stem warm_start_grid_tiny \
                --variants sequential-keyframe,sequential-keyframe-grid-eager
              bench "$cabinet" --presets tiny --variants sequential-odometry,sequential-odometry-grid-eager \
                --set dataset.width=640 --set dataset.height=480 --stem grid_eager_cabinet ;;
    precompile-build)  # issue 34: one run (torch.compile'd) whose end waits for the align iterations' packages, built in parallel child processes, to carry into later calls
              bench synthetic-tum --presets tiny --set synthetic.frames=40 --stem precompile_build_tiny --variants sequential-keyframe-precompiled
              cp -r .device/cache/gsplatam/aoti "$out/" 2>/dev/null ;;
    warm-start-precompile)  # issue 34: the align iterations as AOTInductor packages: the first precompiled cell builds them beside its run (waiting at its end), the rest load them
              bench synthetic-tum --presets tiny --repeats 2 --set synthetic.frames=40 --stem warm_start_precompile_tiny \
                --variants sequential-keyframe,sequential-keyframe-precompiled,process-precompiled
              cp -r .device/cache/gsplatam/aoti "$out/" 2>/dev/null ;;  # the packages built, to carry into later calls
    precompile-cabinet)  # the packages against torch.compile where every frame is a large step (builds the cabinet's own packages)
              bench "$cabinet" --presets tiny --variants sequential-odometry,sequential-odometry-precompiled \
                --set dataset.width=640 --set dataset.height=480 --stem precompile_cabinet ;;
    pace-thread) bench synthetic-tum --presets tiny,small --variants sequential,process,thread --stem pace_thread ;;  # 200 frames
    odometry-slow)  # the slow TUM sample and the generator's fast loops, where odometry must not hurt
              bench "$tum" synthetic-fast-loops --presets tiny --variants process,process-odometry,sequential,sequential-odometry \
                --set dataset.width=640 --set dataset.height=480 --stem odometry_slow_tiny ;;
    odometry-cabinet-sequential) bench "$cabinet" --presets tiny --variants sequential,sequential-odometry \
                --set dataset.width=640 --set dataset.height=480 --stem odometry_cabinet_sequential_tiny ;;
    drift-base) bench "$cabinet" "$tum" synthetic-fast-loops --presets base --variants default,process \
                  --set dataset.width=640 --set dataset.height=480 --stem drift_base
                python3 bench/loop_recall.py --out "$out" --data "$cabinet" --data "$tum" --size 640x480 --trap \
                  $([ -n "${DRY:-}" ] && echo --size 80x60 --max-pairs 2) 2>&1 | tail -n 3 ;;
    loops) bench synthetic-loops synthetic-trap --presets tiny --variants default,loops --stem loops_tiny
           bench synthetic-loops --presets small --variants ${SMALL_VARIANTS:-default,loops} --stem loops_small ;;
    soak) python3 bench/live_latency.py --out "$out" --size 256x192 --seconds ${SOAK_S:-240} --sample-s 10 2>&1 | tail -n 4 ;;
    tiny|small|base) bench synthetic --presets "$part" --stem "$part" ;;
    schedule) bench synthetic synthetic-tum "$tum" --presets tiny,small --variants sequential,process --repeats 2 --stem schedule ;;
    mapping) bench synthetic --presets tiny --variants default,views2,views3,selective-adam --stem mapping_options ;;
    tum) bench synthetic-tum --presets tum --stem tum_synthetic ;;
    ssim) python3 bench/ssim_blur.py --out "$out" 2>&1 | tail -n 20 ;;
    mapping-parity) python3 bench/mapping_parity.py --out "$out" 2>&1 | grep -v Warning | tail -n 20 ;;
    process-smoke) python3 -m pipeline run --preset tiny --set slam.schedule=process --set synthetic.frames=40 \
                     --quiet --output /tmp/smoke --name process 2>&1 | tail -n 25
                   cp /tmp/smoke/process/metrics.json "$out/process_smoke.json" ;;
    schedules-final) bench synthetic-tum "$tum" synthetic --presets tiny --variants sequential,process,process-views2 \
                       --stem schedules_tiny
                     bench "$tum" --presets base --variants sequential --stem schedules_base ;;
    schedules-tiny) bench synthetic-tum "$tum" synthetic --presets tiny \
                      --variants sequential,process,process-views2 --stem schedules_tiny ;;
    schedules-small) bench synthetic-tum "$tum" synthetic --presets small --variants sequential,process --stem schedules_small ;;
    schedules-base) bench synthetic-tum "$tum" --presets base --variants sequential --stem schedules_base ;;
    process-options) bench synthetic-tum --presets tiny \
                       --variants process,process-lead1,process-no-refine,process-fixed-poses,process-no-sample,process-final \
                       --stem process_options ;;
    smoke) bench synthetic --presets tiny --set synthetic.frames=60 --variants sequential,process,views2,selective-adam --stem smoke ;;
    exports) python3 -m pipeline run --preset tiny --quiet --output /tmp/exports --name tiny 2>&1 | tail -n 3
             for fmt in nerfstudio splat ply pointcloud mesh; do  # mesh needs open3d (the mesh extra) there
               start=$SECONDS
               python3 -m pipeline export /tmp/exports/tiny --to $fmt 2>&1 | tail -n 1
               echo "export $fmt: $((SECONDS - start)) s"
             done 2>&1 | tee "$out/exports.txt"
             ls -la /tmp/exports/tiny /tmp/exports/tiny/nerfstudio | head -n 40 >> "$out/exports.txt" ;;
    viewer) python3 bench/viewer_overhead.py --out "$out" --preset tiny --frames 200 2>&1 | grep -v "^gsplatam" | tail -n 12 ;;
    ray-live) python3 bench/ray_scale.py --out "$out" --stem ray_live --parts live --phone "${RAY_PHONE:-nerfcapture}" 2>&1 | grep -v "WARNING\|INFO" | tail -n 20 ;;
    ray-matrix) python3 bench/ray_scale.py --out "$out" --stem ray_matrix --parts matrix 2>&1 | grep -v "WARNING\|INFO" | tail -n 20 ;;
    *) echo "unknown part $part"; exit 2 ;;
  esac
}
for part in "$@"; do
  echo "== $part (suite at ${SECONDS}s)"
  run_part &  # waited for, not in the foreground: a TERM (an outer timeout) packs what is done at once, not after the part
  wait $!
  [ $? -eq 2 ] && exit 2
  tar -czf "$dest/results.tar.gz" -C "$out" .  # after every part: a call killed at its time limit keeps what was done
done
echo "== done (suite at ${SECONDS}s)"
