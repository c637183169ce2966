#!/usr/bin/env bash
# The whole test suite: sets up (idempotent), then the Rust tests (release, plus the f64
# finite-difference gradient tests, and the rasterizer's on aarch64 under qemu) and pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
cargo test --release --workspace
cargo test --release -p legslam-core --features f64
bash scripts/test_aarch64.sh
.venv/bin/python -m pytest -q tests
