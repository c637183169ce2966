#!/usr/bin/env bash
# The rasterizer's tests on aarch64, where it composites with NEON: the engine cross-compiled
# and its tests run under qemu's user-mode emulation (correctness only: emulated timings say
# nothing). Installs what it needs (Debian's qemu-user and aarch64 gcc, rustup's aarch64
# standard library) where it can; where it cannot, it says what is missing and exits 0 unless
# LEGSLAM_REQUIRE_AARCH64=1, so that a machine without them still runs the rest of the suite.
#
#   bash scripts/test_aarch64.sh            # the raster tests (about a minute once built)
#   bash scripts/test_aarch64.sh --all      # every legslam-core test (about ten minutes)
set -euo pipefail
cd "$(dirname "$0")/.."
target=aarch64-unknown-linux-gnu
sysroot=/usr/aarch64-linux-gnu

missing() {
    echo "test_aarch64: $1; the NEON path was not tested" >&2
    [ "${LEGSLAM_REQUIRE_AARCH64:-0}" = 1 ] && exit 1
    exit 0
}

if ! command -v qemu-aarch64 > /dev/null || ! command -v aarch64-linux-gnu-gcc > /dev/null \
    || [ ! -d "$sysroot/lib" ]; then
    if command -v apt-get > /dev/null && [ "$(id -u)" = 0 ]; then
        packages=(qemu-user gcc-aarch64-linux-gnu libc6-dev-arm64-cross)
        # Once more after refreshing the package lists (a fresh machine may have none).
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q "${packages[@]}" > /dev/null 2>&1 \
            || { apt-get update -q > /dev/null 2>&1 \
                && DEBIAN_FRONTEND=noninteractive apt-get install -y -q "${packages[@]}" > /dev/null; } \
            || missing "apt-get could not install ${packages[*]}"
    else
        missing "qemu-aarch64 and aarch64-linux-gnu-gcc are not installed (Debian: apt-get install qemu-user gcc-aarch64-linux-gnu libc6-dev-arm64-cross)"
    fi
fi
if ! rustup target list --installed 2> /dev/null | grep -qx "$target"; then
    rustup target add "$target" > /dev/null 2>&1 \
        || missing "rustup could not install the $target standard library"
fi

export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER="qemu-aarch64 -L $sysroot"
args=(--release -p legslam-core --target "$target" --target-dir target/aarch64)
if [ "${1:-}" = --all ]; then
    cargo test "${args[@]}"
else
    cargo test "${args[@]}" --lib raster::lanes
    cargo test "${args[@]}" --test raster_simd --test raster_kept --test raster_reference \
        --test raster_scratch
fi
