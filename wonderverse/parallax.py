"""Is there parallax to reconstruct from? A cheap look at a clip before the mappers run.

SfM can only triangulate what the camera sees from places far enough apart. When it does not (a camera
that stays put, only turns, or looks at one flat surface), COLMAP's mappers fail slowly: on a 49-frame
CogVideoX clip turning 0.13° per frame the global, incremental and held-focal mappers took 49 s on the quiet
2-core machine before the check blamed a "translation jump". `measure_parallax` looks at a few frames
instead (`parallax_frames`, spread over the clip): SIFT, matching of consecutive ones plus the widest pairs
(first-last, first-middle, middle-last), and COLMAP's two-view geometries with their relative poses. Per
pair it measures

- how well one homography explains the inlier matches (median distance in pixels between where the
  homography sends a feature and where it was matched): a camera that only turns, or a flat scene, is
  explained to within noise, and then there is no parallax to triangulate from;
- the median triangulation angle of the inliers under the pair's relative pose (essential matrix or
  homography decomposition, with the K given, usually a guess): what the mappers would triangulate with.

`ParallaxReport.verdict` turns that into a reason in words, or "" when there is parallax (or too few
matched pairs to judge: the mappers and their gates then say what is wrong). Measured here (9 frames,
guessed 60° K, one thread; `benchmarks.real_clips`): the widest pair's angle was 2.5° on the near-static
CogVideoX clip `gallery_4` and 2.7° on the slow drift `gallery_1` (whose held-focal model, 85 s of
mapping, later showed a median 3.7° per point); 4.5-75° on every clip with camera motion (CameraCtrl gifs,
CogVideoX `train`/`horse`/`gallery_2`), 8-73° on the seven RealEstate10K clips and 58° on the fox capture.
On the lawn of `kitten` one homography explains 90 % of every pair's matches to 0.58 px; on every other
clip some pair is 6 px off or more (46 px on 20 fox frames whose median match lies on the table, 0.86 px).

pycolmap is imported inside the functions (importing this module stays cheap).
"""

from __future__ import annotations

import itertools
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# Fewest inlier matches for a pair to count as matched (COLMAP's own default for a verified pair).
MIN_PAIR_INLIERS = 15
# Share of the chain pairs (consecutive frames of the subset) that must match for a verdict.
MIN_MATCHED_SHARE = 0.5


@dataclass
class PairParallax:
    """One matched pair: frames i < j (indices into the clip), COLMAP's configuration name, inlier count,
    median homography residual (px, NaN without H), median triangulation angle (deg, NaN without a
    relative pose), the relative rotation angle (deg, NaN without a relative pose) and the 90th
    percentile of the homography residual (px)."""

    i: int
    j: int
    config: str
    inliers: int
    homography_px: float
    tri_angle_deg: float
    rotation_deg: float
    homography_p90_px: float = float("nan")


@dataclass
class ParallaxReport:
    """What `measure_parallax` saw.

    frames: clip indices looked at; pairs: the pairs matched (each a PairParallax); chain_pairs: how many
    of them are consecutive frames of the subset; focal_px: the focal length the angles assume;
    seconds: wall time of the look."""

    frames: list[int]
    pairs: list[PairParallax]
    chain_pairs: int
    focal_px: float
    seconds: float
    notes: list[str] = field(default_factory=list)

    @property
    def matched(self) -> list[PairParallax]:
        return [p for p in self.pairs if p.inliers >= MIN_PAIR_INLIERS]

    @property
    def homography_px(self) -> float:
        """The largest 90th-percentile homography residual over the matched pairs (px): small when one
        homography explains (nearly) every match of every pair. The 90th percentile, not the median: where
        most matches lie on one plane (the fox capture's table), the rest still show the parallax."""
        vals = [p.homography_p90_px for p in self.matched]
        return float(max(vals)) if vals and all(np.isfinite(vals)) else float("nan")

    @property
    def widest(self) -> PairParallax | None:
        """The matched pair with the largest median triangulation angle (None: no relative pose)."""
        posed = [p for p in self.matched if np.isfinite(p.tri_angle_deg)]
        return max(posed, key=lambda p: p.tri_angle_deg) if posed else None

    @property
    def rotation_deg_per_frame(self) -> float:
        """Median over posed pairs of the relative rotation divided by the frames between them."""
        vals = [p.rotation_deg / (p.j - p.i) for p in self.matched if np.isfinite(p.rotation_deg)]
        return float(np.median(vals)) if vals else float("nan")

    def verdict(self, min_tri_angle_deg: float, homography_px: float) -> str:
        """Why there is too little parallax to reconstruct, in words; "" when there is enough, or when too
        few pairs matched to say (`MIN_MATCHED_SHARE` of the chain pairs)."""
        adjacent = set(itertools.pairwise(self.frames))
        chain = [p for p in self.matched if (p.i, p.j) in adjacent]
        if len(chain) < max(1, int(np.ceil(MIN_MATCHED_SHARE * self.chain_pairs))):
            return ""
        turn = self.rotation_deg_per_frame
        turns = f"the camera turns {turn:.2f}° per frame" if np.isfinite(turn) else "the camera's turn is unknown"
        h = self.homography_px
        if np.isfinite(h) and h <= homography_px:
            return (
                f"too little parallax to reconstruct: one homography explains 90% of the matches of every pair "
                f"of frames to {h:.2f} px (a camera that only turns, or a flat scene; {turns})"
            )
        w = self.widest
        if w is not None and w.tri_angle_deg < min_tri_angle_deg:
            px = np.radians(w.tri_angle_deg) * self.focal_px
            return (
                f"too little parallax to reconstruct: {turns}, and frames {w.i} and {w.j}, the pair that sees most, "
                f"see a median triangulation angle of {w.tri_angle_deg:.1f}° (~{px:.0f} px of parallax; "
                f"SfM is not tried below {min_tri_angle_deg:g}°)"
            )
        return ""

    def to_attrs(self) -> dict[str, Any]:
        """JSON-ready summary (NaN -> None) for store attributes."""
        w = self.widest

        def clean(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {
            "frames": list(self.frames),
            "pairs_matched": len(self.matched),
            "pairs": len(self.pairs),
            "homography_px": clean(self.homography_px),
            "max_tri_angle_deg": clean(w.tri_angle_deg) if w else None,
            "widest_pair": [w.i, w.j] if w else None,
            "rotation_deg_per_frame": clean(self.rotation_deg_per_frame),
            "focal_px": float(self.focal_px),
            "seconds": float(self.seconds),
            "notes": list(self.notes),
        }

    def rows(self) -> list[dict[str, Any]]:
        return [asdict(p) for p in self.pairs]


def subset(n_frames: int, n: int) -> np.ndarray:
    """Indices of `n` frames spread evenly from the first to the last (all when there are fewer)."""
    return np.unique(np.round(np.linspace(0, n_frames - 1, min(n, n_frames))).astype(int))


def pairs_to_look_at(n: int) -> list[tuple[int, int]]:
    """Positions (a < b) in a subset of n frames: consecutive ones, then first-last, first-middle, middle-last."""
    m = n // 2
    chain = {(k, k + 1) for k in range(n - 1)}
    wide = {(0, n - 1), (0, m), (m, n - 1)} - chain - {(0, 0), (m, m)}
    return sorted(chain) + sorted(p for p in wide if p[0] < p[1])


def triangulation_angles(p1: np.ndarray, p2: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Triangulation angle (degrees) of each match p1[k] <-> p2[k] ((N,2) pixels, centres at +0.5) under the
    relative pose x2 = R x1 + t (any scale) and intrinsics K (3,3): the angle at the midpoint-triangulated
    point between the rays from the two camera centres (`two_view.triangulated_depths`); 0 for points behind
    either camera or a pose without translation."""
    from wonderverse.two_view import triangulated_depths

    if not np.linalg.norm(t) > 0:
        return np.zeros(len(p1))
    Kinv = np.linalg.inv(K)
    r1 = np.c_[p1, np.ones(len(p1))] @ Kinv.T
    r2 = np.c_[p2, np.ones(len(p2))] @ Kinv.T
    r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
    r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
    return triangulated_depths(r1, r2, R, t)[1]


def homography_residuals(p1: np.ndarray, p2: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Distance (px) between H p1 and p2 for each match ((N,2) pixels)."""
    q = np.c_[p1, np.ones(len(p1))] @ np.asarray(H, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        q = q[:, :2] / q[:, 2:]
    r = np.linalg.norm(q - p2, axis=1)
    return np.where(np.isfinite(r), r, np.inf)


def read_pairs(db_path: Path, index: dict[str, int], K: np.ndarray) -> list[PairParallax]:
    """Every two-view geometry in the database as a PairParallax (frames by `index`: image name -> clip
    index), the angles under K (3,3) in the database's pixels."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        images = {im.image_id: im.name for im in db.read_all_images()}
        keypoints = {iid: np.asarray(db.read_keypoints(iid), dtype=np.float64)[:, :2] for iid in images}
        pair_ids, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    out = []
    for pid, g in zip(pair_ids, geometries, strict=True):
        a, b = pycolmap.pair_id_to_image_pair(pid)
        m = np.asarray(g.inlier_matches, dtype=np.int64).reshape(-1, 2)
        p1, p2 = keypoints[a][m[:, 0]], keypoints[b][m[:, 1]]
        h = h90 = tri = rot = float("nan")
        if len(m) and g.H is not None:
            r = homography_residuals(p1, p2, g.H)
            h, h90 = float(np.median(r)), float(np.percentile(r, 90))
        pose = g.cam2_from_cam1
        if len(m) and pose is not None:
            R, t = pose.rotation.matrix(), np.asarray(pose.translation, dtype=np.float64)
            tri = float(np.median(triangulation_angles(p1, p2, K, R, t)))
            rot = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
        i, j = index[images[a]], index[images[b]]
        if i > j:
            i, j = j, i
        out.append(PairParallax(i, j, str(g.config).rsplit(".", 1)[-1], len(m), h, tri, rot, h90))
    return sorted(out, key=lambda p: (p.i, p.j))


def measure_parallax(
    image_files: Sequence[Path],
    size_wh: tuple[int, int],
    K: np.ndarray | None,
    n_frames: int,
    max_image_size_px: int,
    max_num_features: int,
    random_seed: int = 0,
    num_threads: int = 1,
    workdir: Path | None = None,
) -> ParallaxReport:
    """Look at `n_frames` of the clip's frames (`image_files`, all of size `size_wh` (W,H), in clip order):
    SIFT (`max_image_size_px`, `max_num_features`), matching and verification of `pairs_to_look_at`, with K
    (3,3, pixels; None: COLMAP's 1.2·max(W,H) focal, centred) given to COLMAP as a prior so that each pair
    gets a relative pose. Returns the ParallaxReport; never raises on bad content (no features: no pairs)."""
    import pycolmap

    from wonderverse.features import extract_features, match_pairs

    t0 = time.perf_counter()
    w, h = size_wh
    if K is None:
        f = 1.2 * max(w, h)
        K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    K = np.asarray(K, dtype=np.float64)
    idx = subset(len(image_files), n_frames)
    with tempfile.TemporaryDirectory(prefix="wv-parallax-") as tmp:
        work = Path(workdir) if workdir is not None else Path(tmp)
        image_dir = work / "images"
        image_dir.mkdir(parents=True, exist_ok=True)
        names = []
        for i in idx:
            src = Path(image_files[i])
            name = f"{i:06d}{src.suffix.lower()}"
            link = image_dir / name
            if link.is_symlink() or link.exists():
                link.unlink()
            link.symlink_to(src.resolve())
            names.append(name)
        db_path = work / "database.db"
        db_path.unlink(missing_ok=True)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"  # fx and fy as given: the angles need the pixel aspect too
        reader.camera_params = ",".join(repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        extract_features(db_path, image_dir, names, reader, max_image_size_px, max_num_features, num_threads)
        pairs = [(names[a], names[b]) for a, b in pairs_to_look_at(len(names))]
        match_pairs(db_path, pairs, random_seed, num_threads, relative_pose=True)
        found = read_pairs(db_path, {name: int(i) for name, i in zip(names, idx, strict=True)}, K)
    return ParallaxReport(
        frames=[int(i) for i in idx],
        pairs=found,
        chain_pairs=len(idx) - 1,
        focal_px=float(0.5 * (K[0, 0] + K[1, 1])),
        seconds=time.perf_counter() - t0,
    )
