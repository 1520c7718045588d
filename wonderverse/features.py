"""SIFT features and their matching with pycolmap (CPU), into a COLMAP database: what SfM (`wonderverse.sfm`),
its extension (`wonderverse.sfm_extend`) and the parallax look before mapping (`wonderverse.parallax`) share.

Settings are spelled out as arguments, not an `SfmParams`: the parallax look runs with fewer features than the
mappers. Matching never uses loop detection (offline it aborts the process) and always runs over an explicit
list of image pairs, so that the caller's frame order counts, not the order of the image names.

pycolmap is imported inside the functions so that importing this module stays cheap.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pycolmap


def extract_features(
    db_path: Path,
    image_dir: Path,
    names: list[str],
    reader: pycolmap.ImageReaderOptions,
    max_image_size_px: int,
    max_num_features: int,
    num_threads: int,
    peak_threshold: float | None = None,
) -> None:
    """SIFT on `names` (files in `image_dir`) into the database at `db_path`, all with one camera described by
    `reader`; images are downscaled to `max_image_size_px` for SIFT (keypoints in full-size pixels);
    `peak_threshold` None is COLMAP's."""
    import pycolmap

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.use_gpu = False
    extraction.max_image_size = max_image_size_px
    extraction.sift.max_num_features = max_num_features
    if peak_threshold is not None:
        extraction.sift.peak_threshold = peak_threshold
    pycolmap.extract_features(
        db_path,
        image_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )


def match_pairs(
    db_path: Path, pairs: list[tuple[str, str]], random_seed: int, num_threads: int, relative_pose: bool = False
) -> pycolmap.TwoViewGeometryOptions:
    """Match and geometrically verify the given image-name pairs in the database (a `pairs.txt` beside it);
    `relative_pose` also stores each pair's relative pose. Returns the verification options used."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = random_seed
    verification.compute_relative_pose = relative_pose
    if not pairs:
        return verification
    pair_file = db_path.with_name("pairs.txt")
    pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pair_file
    pycolmap.match_image_pairs(
        db_path,
        matching_options=matching,
        pairing_options=pairing,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )
    return verification


def sequential_pairs(n_frames: int, overlap: int, quadratic: bool) -> list[tuple[int, int]]:
    """Index pairs (i, j), i < j, that COLMAP's sequential matcher (4.2.1) chooses for frames in this order:
    each frame with the next `overlap` ones or, when `quadratic`, with those 2^k ahead (k < overlap) instead.

    Generated here rather than by `match_sequential`, which orders frames by image name: our names are stable
    ids (`s002_0005.png`), and a left extension plays its frames reversed and before the others."""
    pairs = []
    for i in range(n_frames):
        for k in range(overlap):
            j = i + (1 << k if quadratic else k + 1)
            if j >= n_frames:
                break
            pairs.append((i, j))
    return pairs
