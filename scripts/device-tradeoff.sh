#!/usr/bin/env bash
# The GPU half of `python -m benchmarks.tradeoff` on the lent device (CUDA, no network, a 64 MiB carry per
# call, idle machines given back after 30 s), in calls made back to back:
#   stage DIR   copy a carried folder of wheels (or parts of one) to /tmp/stage
#   install     join split wheels, install everything into /tmp/site, build gsplat, check imports (and
#               run scripts/gpu_video_diffusion.py unless SKIP_DIFFUSION is set)
#   start P,..  run `benchmarks.tradeoff --one` for each preset x scene at once, in the background
#               (SCENES="indoor" picks scenes; ONE_ARGS="--mesh-voxels 0.0039" adds arguments)
#   collect     wait for them (at most $WAIT_S s); rows into $OUT/tradeoff_gpu.json, logs into $OUT
#   bench M A.. run `python3 -m benchmarks.M A..` in the background (another benchmark on the same install)
#   wait-bench  wait for it (at most $WAIT_S s); its output into $OUT/M.log
# `install` checks the imports the tradeoff needs; IMPORTS="open3d gsplat torch" checks fewer (what was staged).
# What the image lacks, carried (cp312 manylinux wheels; the two large ones split with `split -b 55m` into
# NAME.whl.part-aa, -ab, ... across the carried folders): open3d-cpu 0.19.0 (100 MB), imageio-ffmpeg (68 MB:
# the image has no ffmpeg), pycolmap 4.2.1, zarr and its codecs, pydantic, dask/distributed and their small
# dependencies, trimesh, plyfile, rich, the gsplat 1.5.3 sdist, diffusers; and `.gl/` (the libGL/libglvnd
# .debs the device README names: open3d's module links libGL.so.1), unpacked with dpkg -x by `install`.
# Fewer calls: the wheels installed here for cp312 (`pip install --target DIR --python-version 3.12
# --only-binary=:all: --platform ...`) and packed as `tar cf - -C DIR . | xz -9` (split like a wheel when large)
# are unpacked into /tmp/site. A machine left idle 30 s between calls is given back and starts bare, so stage
# and install back to back; `install` stops when open3d did not arrive.
# open3d imports its plotly viewer and its ML package eagerly; the installed copy makes both optional.
set -uo pipefail
REPO=$(pwd)
OUT=${OUT:-/tmp/out}
RUN=/tmp/tradeoff
mkdir -p "$OUT" /tmp/stage "$RUN"
export PYTHONUNBUFFERED=1 MAX_JOBS=16 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} CUDA_HOME=/usr/local/cuda
export PYTHONPATH=/tmp/site:$REPO
case "$1" in
stage) cp -r "$REPO/$2"/. /tmp/stage/ && ls -la /tmp/stage | tail -n +2 | wc -l ;;
install)
  for f in "$REPO"/.gl/*.deb; do dpkg -x "$f" /; done; ldconfig
  cd /tmp/stage
  for first in *.part-aa; do cat "${first%.part-aa}".part-* > "${first%.part-aa}" && rm "${first%.part-aa}".part-*; done
  mkdir -p /tmp/site
  for t in *.tar.xz; do [ -e "$t" ] && { tar xJf "$t" -C /tmp/site || exit 1; }; done
  if ls ./*.whl > /dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site ./*.whl || exit 1
  fi
  [ -e /tmp/site/open3d ] || { echo "open3d missing: was every part staged on this machine?"; ls /tmp/stage; exit 1; }
  sed -i -E 's/^from .draw_plotly import (draw_plotly|draw_plotly_server)$/try:\n    from .draw_plotly import \1\nexcept ImportError:\n    pass/' \
    /tmp/site/open3d/visualization/__init__.py
  sed -i -E 's/^( *)import open3d\.ml$/\1try:\n\1    import open3d.ml\n\1except ImportError:\n\1    pass/' /tmp/site/open3d/__init__.py
  (cd /tmp && tar xzf /tmp/stage/gsplat-1.5.3.tar.gz && cd gsplat-1.5.3 &&
    python3 -m pip install -q --no-build-isolation --no-deps --no-index --target /tmp/site . > "$OUT/build.log" 2>&1) ||
    { tail -20 "$OUT/build.log"; exit 1; }
  [ -n "${SKIP_DIFFUSION:-}" ] || python3 "$REPO/scripts/gpu_video_diffusion.py" 2>&1 | tee "$OUT/gpu_video_diffusion.log" | tail -12
  if [ -n "${IMPORTS:-}" ]; then
    python3 -c "import ${IMPORTS// /, }, torch; print('imports ok', torch.cuda.get_device_name())"
  else
    python3 -c "import open3d, pycolmap, zarr, gsplat, torch, imageio, trimesh, dask.distributed
from tasks import STEPS; import benchmarks.tradeoff
print('imports ok', open3d.__version__, pycolmap.__version__, gsplat.__version__, torch.cuda.get_device_name())"
  fi ;;
bench)
  setsid nohup python3 -m "benchmarks.$2" "${@:3}" > "$RUN/$2.log" 2>&1 &
  sleep 5; tail -3 "$RUN/$2.log" ;;
wait-bench)
  end=$((SECONDS + ${WAIT_S:-540}))
  while pgrep -f "benchmarks.$2" > /dev/null && [ $SECONDS -lt $end ]; do sleep 10; done
  grep -v "^[EWI]2026" "$RUN/$2.log" > "$OUT/$2.log"; tail -25 "$OUT/$2.log" ;;
start)
  IMAGEIO_FFMPEG_EXE=$(python3 -c "import imageio_ffmpeg; print(imageio_ffmpeg.get_ffmpeg_exe())")
  export IMAGEIO_FFMPEG_EXE
  IFS=, read -ra presets <<< "$2"
  # shellcheck disable=SC2086  # SCENES and ONE_ARGS split into words on purpose
  for p in "${presets[@]}"; do for s in ${SCENES:-outdoor indoor}; do
    setsid nohup python3 -m benchmarks.tradeoff --one "$p" "$s" "$RUN/$p-$s" ${ONE_ARGS:-} > "$RUN/$p-$s.out" 2> "$RUN/$p-$s.err" &
  done; done
  sleep 5; ls "$RUN" ;;
collect)
  end=$((SECONDS + ${WAIT_S:-540}))
  while pgrep -f "benchmarks.tradeoff --one" > /dev/null && [ $SECONDS -lt $end ]; do sleep 10; done
  for f in "$RUN"/*.err; do echo "== $f"; grep -v "^[EWI]2026" "$f" | tail -3; done
  python3 - "$RUN" "$OUT/tradeoff_gpu.json" <<'PY'
import json, pathlib, sys
rows = []
for f in sorted(pathlib.Path(sys.argv[1]).glob("*.out")):
    lines = [x for x in f.read_text().splitlines() if x.startswith("{")]
    print(f.name, "done" if lines else "not finished")
    rows += [json.loads(lines[-1])] if lines else []
pathlib.Path(sys.argv[2]).write_text(json.dumps(rows, indent=1))
PY
  tar czf "$OUT/tradeoff_logs.tgz" -C "$RUN" $(cd "$RUN" && ls *.err *.out) ;;
esac
