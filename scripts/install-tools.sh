#!/usr/bin/env bash
# The npm tools the test suite runs on the outputs, pinned by tools/package-lock.json (Khronos gltf-validator,
# and the web-splat tools: splat-transform, three.js's glTF loader). Only the tests and benchmarks need them:
# `view` and `studio` serve the viewer's built files shipped in the Python package (flows/viewer_assets/).
# Needs Node.js >= 18 with npm. Does nothing when node_modules is newer than the lock
# file (npm ci writes node_modules/.package-lock.json last).
set -euo pipefail
cd "$(dirname "$0")/../tools"
if ! command -v npm >/dev/null; then
  echo "install-tools: npm not found (install Node.js 20 with npm); the tests that need it will skip" >&2
  exit 0
fi
[ node_modules/.package-lock.json -nt package-lock.json ] && exit 0
npm ci --no-audit --no-fund --loglevel=error
