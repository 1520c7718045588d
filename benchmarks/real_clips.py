"""Real footage and real AI clips through `reconstruct`'s steps: poses against reference paths, parallax verdicts.

Every clip in `../shared/data` with a reference path, and every AI clip, runs as `wonderverse reconstruct CLIP`
would (files backend, preview preset, one clip per scene, `on_failure: keep_best`) up to `poses`, each in a
fresh temporary scene:

- the 7 RealEstate10K clips (`cameractrl_re10k/reference_videos`, pose files: W2C, true intrinsics), twice:
  with no FOV given (K guessed, then estimated by SfM) and with their true horizontal FOV given;
- the fox capture (`instant_ngp_fox/images`, `transforms.json`: OpenGL camera-to-world), guessed K;
- the AI clips: the six CogVideoX samples (no path; `gallery_1`, `gallery_4`, `kitten` are the near-static
  ones per their SOURCE.md) and the six CameraCtrl gifs (three have the path they were conditioned on).

Per clip: frames registered by the global poses (of those stitched), whether the check flagged it and why,
ATE of the global poses after a Sim(3) as a share of the reference path, the rotation error per step (mean
and max over consecutive frames, degrees: the relative rotation against the reference's), seconds in
`check` and `poses` (a `poses` that stops for too little parallax counts until it stops), where K came from
(`k_source`) and its horizontal FOV. Then one RealEstate10K clip (`3c35…`, guessed K) goes on to outputs
(no depth model: colours alone) for its held-out PSNR.

Last-line keys:
`re10k_ate_max_frac`, `re10k_ate_median_frac`: over the RealEstate10K clips with no FOV given (target
≤ 0.01 and ≤ 0.005); `re10k_given_ate_max_frac`: the same with their true FOV given;
`re10k_flagged`: RealEstate10K clips the check flags with no FOV given (target 0);
`fox_ate_frac`: the fox capture, no FOV given (target ≤ 0.001);
`ai_static_flagged`: near-static CogVideoX clips flagged for too little parallax (of
`ai_static_clips`); `ai_static_seconds_max`: the slowest of them, check + poses seconds (target ≤ 20);
`ai_moving_parallax_flagged`: AI clips with camera motion flagged for parallax (should be 0);
`real_psnr_heldout`: held-out PSNR (dB) of `3c35…` taken to outputs (left out with --quick);
`seconds`: the whole run; `load_1min`: the machine's load average when it started (the machine is shared).
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.common import parse_args, report
from flows.pipeline import StepFailed, execute
from wonderverse.camera import geodesic_angle
from wonderverse.config import build_config
from wonderverse.metrics import ate
from wonderverse.schema import ATTEMPT, SFM, SPLATS
from wonderverse.store import SceneStore

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RE10K = DATA / "cameractrl_re10k"
FOX = DATA / "instant_ngp_fox"
COGVIDEOX = DATA / "cogvideox_samples"
NEAR_STATIC = ("cogvideox2b_gallery_1", "cogvideox2b_gallery_4", "gradio_example_kitten")  # their SOURCE.md
PSNR_CLIP = "3c35b868a8ec3433"


def re10k_poses(stem: str) -> tuple[np.ndarray, float]:
    """(W2C (T,4,4) OpenCV, horizontal FOV in degrees) of a RealEstate10K pose file (SOURCE.md)."""
    rows = [ln.split() for ln in (RE10K / "pose_files" / f"{stem}.txt").read_text().splitlines()[1:] if ln.strip()]
    vals = np.array([[float(x) for x in r] for r in rows])
    w2c = np.tile(np.eye(4), (len(vals), 1, 1))
    w2c[:, :3, :4] = vals[:, 7:19].reshape(-1, 3, 4)
    return w2c, float(np.degrees(2.0 * np.arctan(0.5 / vals[0, 1])))


def fox_poses() -> tuple[np.ndarray, float]:
    """(W2C (T,4,4) OpenCV of the frames `reconstruct` reads from the folder, horizontal FOV in degrees)."""
    from wonderverse.video.files import ClipParams, read_clip

    tj = json.loads((FOX / "transforms.json").read_text())
    w2c = {}
    for f in tj["frames"]:
        c2w = np.array(f["transform_matrix"], dtype=np.float64)
        c2w[:3, :3] = c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenGL -> OpenCV camera axes
        w2c[Path(f["file_path"]).name] = np.linalg.inv(c2w)
    files = sorted((FOX / "images").glob("*.jpg"))
    params = ClipParams()
    clip = read_clip(FOX / "images", params)
    idx = np.round(clip.times_s * params.image_fps).astype(int)  # image folders: frame i at i / image_fps
    return np.stack([w2c[files[i].name] for i in idx]), float(np.degrees(2 * np.arctan(tj["w"] / 2 / tj["fl_x"])))


def rotation_errors_deg(est: np.ndarray, ref: np.ndarray) -> list[float]:
    """Per consecutive pair posed in both: the angle between the estimated and the reference relative
    rotation (W2C, so frame-independent), degrees."""
    out = []
    for i in range(len(est) - 1):
        if np.isfinite(est[i : i + 2]).all() and np.isfinite(ref[i : i + 2]).all():
            r_est = est[i + 1, :3, :3] @ est[i, :3, :3].T
            r_ref = ref[i + 1, :3, :3] @ ref[i, :3, :3].T
            out.append(float(np.degrees(geodesic_angle(r_est, r_ref))))
    return out


def run_clip(clip: Path, options: dict[str, Any], until: str = "poses") -> dict[str, Any]:
    """`reconstruct CLIP` up to `until` in a fresh scene; what the check and the poses said and took."""
    cfg = build_config(
        f"reconstruction of {clip.name}",
        preset="preview",
        overrides={
            "scene": {
                "video": {"backend": "files", "clips": [str(clip)], "options": options},
                "extensions": {"rounds": 0},
            },
            "steps": {"check": {"on_failure": "keep_best"}},
            "execution": {"segment_workers": 1, "renderer": "torch"},
        },
    )
    out: dict[str, Any] = {"error": ""}
    with tempfile.TemporaryDirectory(prefix="wv-real-") as tmp:
        scene = Path(tmp) / "scene"
        try:
            results = execute(scene, cfg, until=until)
        except StepFailed as e:
            results, out["error"] = e.results, str(e.cause)
        seconds = {r.step: r.seconds for r in results}
        store = SceneStore.open(scene)
        at = ATTEMPT.at(seg="s000", attempt=0)
        check, sfm = store.meta(at.check, complete=False), store.meta(at.sfm, complete=False)  # None: absent
        out |= {
            "check_s": seconds.get("check", float("nan")),
            "poses_s": seconds.get("poses", float("nan")),
            "accepted": check.accepted if check is not None else None,
            "reasons": list(check.reasons) if check is not None else [],
            "k_source": sfm.k_source if sfm is not None else "",
            "fov_deg": sfm.fov_deg if sfm is not None else None,
            "n_frames": len(store.array(at.frames)) if store.exists(at.frames) else 0,
        }
        solved = store.meta(SFM.path, complete=False)
        if store.exists(SFM.poses) and solved is not None:
            out |= {"poses": store.array(SFM.poses), "solve": solved.solve}
            out |= {"k_source": solved.k_source or out["k_source"]}
        splats = store.meta(SPLATS.path, complete=False)
        if until == "outputs" and splats is not None:
            out["test_psnr"] = splats.metrics.test_psnr
    return out


def row(name: str, k: str, res: dict[str, Any], ref: np.ndarray | None) -> dict[str, Any]:
    """One table row; `ref`: the reference W2C path (None: the clip has none)."""
    poses = res.get("poses")
    registered = int(np.isfinite(poses).all(axis=(1, 2)).sum()) if poses is not None else 0
    a, rot = float("nan"), []
    if poses is not None and ref is not None and registered >= 3:
        a = ate(poses, ref[: len(poses)])["rmse_frac"]
        rot = rotation_errors_deg(poses, ref[: len(poses)])
    why = "; ".join(res["reasons"]) if res["accepted"] is False else ""
    return {
        "clip": name[:20],
        "K": k,
        "k_source": f"{res['k_source']} {res['fov_deg']:.0f}°" if res.get("fov_deg") else res["k_source"],
        "posed": f"{registered}/{res['n_frames']}",
        "flagged": ("yes: " + why)[:46] if why else "no",
        "ate_%": 100 * a,
        "rot_err_deg": f"{np.mean(rot):.2f}/{np.max(rot):.2f}" if rot else "-",
        "check_s": res["check_s"],
        "poses_s": res["poses_s"],
    }


def main() -> None:
    args = parse_args(__doc__ or "")
    load = os.getloadavg()[0]
    t_all = time.perf_counter()
    print(f"load average at start: {load:.2f} (the machine is shared)", file=sys.stderr, flush=True)
    rows: list[dict[str, Any]] = []
    re10k = sorted(p.stem for p in (RE10K / "reference_videos").glob("*.mp4"))
    if args.quick:
        re10k = [s for s in re10k if s.startswith(("3c35", "0f47"))]
    guessed_ate, given_ate, flagged = [], [], 0
    for stem in re10k:
        ref, fov = re10k_poses(stem)
        clip = RE10K / "reference_videos" / f"{stem}.mp4"
        for k, options in (("guessed", {}), ("given", {"fov_deg": fov})):
            res = run_clip(clip, options)
            r = row(stem, k, res, ref)
            rows.append(r)
            (guessed_ate if k == "guessed" else given_ate).append(r["ate_%"] / 100)
            flagged += int(k == "guessed" and res["accepted"] is False)
            print(f"{stem} {k}: ATE {r['ate_%']:.3f} % flagged {r['flagged']}", file=sys.stderr, flush=True)

    fox_ate = float("nan")
    if (FOX / "images").is_dir():
        ref, _ = fox_poses()
        res = run_clip(FOX / "images", {})
        r = row("fox", "guessed", res, ref)
        rows.append(r)
        fox_ate = r["ate_%"] / 100
        print(f"fox: ATE {r['ate_%']:.4f} % flagged {r['flagged']}", file=sys.stderr, flush=True)

    ai = sorted(COGVIDEOX.glob("*.mp4")) + sorted((RE10K / "generated_gifs").glob("*.gif"))
    if args.quick:
        ai = [p for p in ai if p.stem in NEAR_STATIC or "train" in p.stem]
    static_flagged, static_seconds, moving_parallax = 0, [], 0
    for clip in ai:
        res = run_clip(clip, {})
        intended = RE10K / "pose_files" / f"{clip.stem[-16:]}.txt"
        ref = re10k_poses(clip.stem[-16:])[0] if clip.suffix == ".gif" and intended.exists() else None
        r = row(clip.stem, "guessed", res, ref)
        rows.append(r)
        parallax = any("parallax" in w for w in res["reasons"])
        if clip.stem in NEAR_STATIC:
            static_flagged += int(parallax)
            static_seconds.append(res["check_s"] + (res["poses_s"] if np.isfinite(res["poses_s"]) else 0.0))
        else:
            moving_parallax += int(parallax)
        print(f"{clip.name}: flagged {r['flagged']} ({res['check_s']:.1f} s check)", file=sys.stderr, flush=True)

    psnr = None
    if not args.quick:
        res = run_clip(RE10K / "reference_videos" / f"{PSNR_CLIP}.mp4", {}, until="outputs")
        psnr = res.get("test_psnr")
        print(f"{PSNR_CLIP} to outputs: held-out PSNR {psnr}", file=sys.stderr, flush=True)

    headline: dict[str, Any] = {
        "re10k_ate_max_frac": round(float(np.max(guessed_ate)), 5),
        "re10k_ate_median_frac": round(float(np.median(guessed_ate)), 5),
        "re10k_given_ate_max_frac": round(float(np.max(given_ate)), 5),
        "re10k_flagged": flagged,
        "fox_ate_frac": round(fox_ate, 6),
        "ai_static_flagged": static_flagged,
        "ai_static_clips": len(static_seconds),
        "ai_static_seconds_max": round(float(np.max(static_seconds)), 1) if static_seconds else None,
        "ai_moving_parallax_flagged": moving_parallax,
    }
    if psnr is not None:
        headline["real_psnr_heldout"] = round(float(psnr), 2)
    headline |= {"seconds": round(time.perf_counter() - t_all, 1), "load_1min": round(load, 2)}
    report("real clips through reconstruct's check and poses (ATE: share of the reference path)", rows, headline)


if __name__ == "__main__":
    main()
