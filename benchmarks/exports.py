"""Do the files we write open right in the tools people use, and is the scene upright?

- Scenes: procedural ones, indoor and outdoor, through `outputs` (the preview preset; `--quick`: two smaller ones).
- Up: the outputs' frame records the up direction it chose in the `sfm/` frame; the true up there is the
  procedural world's +Z carried by the rotation that best maps the SfM cameras' orientations onto the true ones
  (chordal mean). `up_error_deg` is the angle between the two.
- Consumers, on every scene's files: pycolmap opens `colmap/sparse/0` (every image present, tracks of ≥ 2
  views), Khronos `gltf-validator` on `mesh.glb` and `splats.glb` (errors, warnings; the splat GLB's only
  expected complaints are the `KHR_gaussian_splatting` attributes the validator predates),
  `@playcanvas/splat-transform` reads `splats.ply` and `splats.spz` (count equal to ours), three.js reads
  `splats.glb` (count), ffmpeg describes the videos (h264, yuv420p) and their moov atom precedes mdat.
- Viewer: `tests/test_view.py`'s Spark-against-our-renderer test is run and its PSNR line read (one code path
  for the measurement, the test's).
- File sizes per format.

Needs `bash scripts/install-tools.sh` (node consumers) and Chromium (viewer). Last-line keys: `up_error_deg_max`,
`viewer_psnr_db` (the lowest over the cameras measured), `consumers_failed` (count of failed checks), `scenes`.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import parse_args, report, table

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools"
SCENES = {
    "christmas (outdoor)": "a small house decorated for Christmas",
    "reading room (indoor)": "a cosy reading room with shelves and armchairs",
    "mountain village (outdoor)": "a snowy mountain village at dusk",
    "kitchen (indoor)": "a modern kitchen with a wooden table",
}
EXPECTED_SPLAT_GLB = "MESH_PRIMITIVE_INVALID_ATTRIBUTE"  # KHR_gaussian_splatting's attributes, unknown to it


def _node(script: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["node", str(script), *args], capture_output=True, text=True, timeout=300, cwd=TOOLS)


def _up_error_deg(store: Any) -> float:
    from tasks.segments import attempt_path
    from wonderverse.schema import OUTPUTS, SFM

    segs, index, poses = store.meta(SFM.path).segments, store.array(SFM.frame_index), store.array(SFM.poses)
    ok = np.isfinite(poses).all(axis=(1, 2))
    gt = {a: store.array(attempt_path(store, segs[a]).gt.poses) for a in np.unique(index[:, 0])}
    gt_w2c = np.stack([gt[a][i] for (a, i), k in zip(index, ok, strict=True) if k])
    U, _, Vt = np.linalg.svd(np.einsum("nji,njk->ik", gt_w2c[:, :3, :3], poses[ok][:, :3, :3]))
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt  # sfm -> true world
    up = np.asarray(store.meta(OUTPUTS.path).frame.up_in_sfm)
    cos = float(np.clip(up @ (R.T @ np.array([0.0, 0.0, 1.0])) / np.linalg.norm(up), -1, 1))
    return float(np.degrees(np.arccos(cos)))


def _consumers(scene: Path, n_gaussians: int) -> list[dict[str, str]]:
    """One row per (file, consumer): pass or fail with the consumer's own words."""
    import pycolmap

    rows: list[dict[str, str]] = []

    def row(file: str, consumer: str, ok: bool, message: str) -> None:
        rows.append({"file": file, "consumer": consumer, "result": "pass" if ok else "FAIL", "message": message})

    rec = pycolmap.Reconstruction(str(scene / "colmap" / "sparse" / "0"))
    missing = [im.name for im in rec.images.values() if not (scene / "colmap" / "images" / im.name).is_file()]
    short = sum(1 for p in rec.points3D.values() if p.track.length() < 2)
    words = f"{rec.num_reg_images()} images ({len(missing)} missing), {rec.num_points3D()} points, {short} short tracks"
    row("colmap/", "pycolmap 4.2.1", not missing and short == 0 and rec.num_points3D() > 0, words)
    for name, allowed in (("mesh.glb", set()), ("splats.glb", {EXPECTED_SPLAT_GLB})):
        run = _node(TOOLS / "validate-gltf.mjs", str(scene / name))
        issues = json.loads(run.stdout)["issues"] if run.stdout.strip() else {}
        codes = {m["code"] for m in issues.get("messages", []) if m["severity"] <= 1}
        ok = run.returncode in (0, 1) and codes <= allowed and issues.get("numWarnings", 1) == 0
        row(name, "gltf-validator", ok, f"{issues.get('numErrors')} errors {sorted(codes)}, "
            f"{issues.get('numWarnings')} warnings")  # fmt: skip
    cli = TOOLS / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"
    for name in ("splats.ply", "splats.spz"):
        run = _node(cli, "-q", str(scene / name), "--stats", "json", "null")
        count = json.loads(run.stdout)["numGaussians"] if run.returncode == 0 else None
        row(name, "@playcanvas/splat-transform 3.7.0", count == n_gaussians, f"{count} Gaussians (ours {n_gaussians})"
            if count is not None else run.stderr.strip()[-200:])  # fmt: skip
    run = _node(TOOLS / "read-splat-glb.mjs", str(scene / "splats.glb"), "1")
    count = json.loads(run.stdout).get("count") if run.returncode == 0 else None
    row("splats.glb", "three.js 0.187 GLTFGaussianSplatLoaderExtension", count == n_gaussians,
        f"{count} Gaussians (ours {n_gaussians})" if count is not None else run.stderr.strip()[-200:])  # fmt: skip
    from imageio_ffmpeg import get_ffmpeg_exe

    for name in ("flythrough.mp4", "novel.mp4"):
        probe = subprocess.run(
            [get_ffmpeg_exe(), "-hide_banner", "-i", str(scene / name)], capture_output=True, text=True
        )
        stream = next((ln.strip() for ln in probe.stderr.splitlines() if "Video:" in ln), "no video stream")
        data = (scene / name).read_bytes()
        faststart = 0 <= data.find(b"moov") < data.find(b"mdat")
        ok = "h264" in stream and "yuv420p" in stream and faststart
        row(
            name, "ffmpeg", ok, f"{stream.split('Video: ', 1)[-1][:60]}; moov {'before' if faststart else 'after'} mdat"
        )
    return rows


def _viewer_psnr() -> float | None:
    """The lowest PSNR of Spark's canvas against our renderer, from tests/test_view.py's own measurement."""
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-s", "tests/test_view.py", "-k", "spark_renders"],
        capture_output=True, text=True, cwd=ROOT, timeout=1800,
    )  # fmt: skip
    m = re.search(r"viewer vs renderer PSNR \(dB\): (\{.*\})", run.stdout)
    return min(float(v) for v in re.findall(r": ([0-9.]+)", m.group(1))) if m else None


def main() -> None:
    args = parse_args(__doc__.splitlines()[0])
    from flows.pipeline import execute
    from wonderverse.config import build_config
    from wonderverse.schema import OUTPUTS
    from wonderverse.store import SceneStore

    scenes = dict(list(SCENES.items())[:2]) if args.quick else SCENES
    video = {"width": 160, "height": 112, "frames_per_segment": 9} if args.quick else {}
    rows, consumer_rows, ups = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name, prompt in scenes.items():
            cfg = build_config(prompt, preset="preview", overrides={"scene": {"video": video}} if video else None)
            scene = Path(tmp) / re.sub(r"\W+", "-", name)
            execute(scene, cfg)
            store = SceneStore.open(scene)
            up = _up_error_deg(store)
            ups.append(up)
            kept = store.meta(OUTPUTS.path).pruned.after
            sizes = {f: (scene / f).stat().st_size for f in ("splats.ply", "splats.spz", "splats.glb", "mesh.glb")}
            rows.append({"scene": name, "up_error_deg": round(up, 3), "gaussians": kept,
                         **{f"{f} kB": round(b / 1e3) for f, b in sizes.items()}})  # fmt: skip
            consumer_rows += [{"scene": name, **r} for r in _consumers(scene, kept)]
            shutil.rmtree(scene, ignore_errors=True)
    psnr = _viewer_psnr()
    table(consumer_rows, "consumers: every output file x every consumer")
    failed = sum(r["result"] != "pass" for r in consumer_rows)
    headline = {
        "up_error_deg_max": round(max(ups), 3),
        "viewer_psnr_db": None if psnr is None else round(psnr, 2),
        "consumers_failed": failed,
        "scenes": len(scenes),
    }
    report("exports", rows, headline)


if __name__ == "__main__":
    main()
