#!/usr/bin/env bash
# Fill the ignored folders that bench/gpu_suite.sh carries to the device machine (Python 3.12,
# no network there): .device/ (the shared gsplat wheel and the base install's wheels the machine
# lacks), .whl-loops/ (GTSAM, for the loop parts) and .data/ (the shared TUM samples).
# Usage, from the repo root: bash bench/prepare_device.sh [SHARED_DIR (default ../shared)]
# Carry at most 64 MiB: .device, .data/tum_fr3_cabinet_kf57 and .whl-loops fit; the TUM sample
# (23 MiB) does not fit beside all three.
set -euo pipefail
shared=${1:-../shared}
bash "$shared/device/prepare.sh"
for folder in .device .data .whl-loops; do
    grep -qx "/$folder/" .git/info/exclude || echo "/$folder/" >> .git/info/exclude
done
wheels() {  # DEST PACKAGE...: binary wheels for the device machine's Python, without their dependencies
    local dest=$1
    shift
    python3 -m pip download -q --only-binary=:all: --no-deps --python-version 3.12 \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform any -d "$dest" "$@"
}
wheels .device tomli-w safetensors tqdm plyfile  # of the base install, not on the machine
wheels .whl-loops gtsam
mkdir -p .data
cp -ru "$shared/data/tum_fr3_cabinet_kf57" "$shared/data/tum_fr1_xyz_37" .data/
du -sh .device .whl-loops .data/*
