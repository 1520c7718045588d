"""The trade-off benchmark's summary: means over the scenes every preset on a machine ran, and the Pareto test."""

from __future__ import annotations

from benchmarks.tradeoff import KEYS, summary


def _row(preset: str, scene: str, seconds: float, fscore: float, psnr: float, machine: str = "gpu") -> dict:
    return dict.fromkeys(KEYS, 0.0) | {
        "preset": preset,
        "scene": scene,
        "machine": machine,
        "seconds": seconds,
        "fscore_1pct": fscore,
        "psnr": psnr,
    }


def test_presets_compare_on_shared_scenes_only() -> None:
    rows = [
        _row("standard", "indoor", 300, 0.6, 32.0),
        _row("standard", "outdoor", 400, 0.2, 30.0),  # high has no outdoor run: left out of the means
        _row("high", "indoor", 1000, 0.7, 34.0),
        _row("high", "indoor", 1200, 0.5, 34.4),  # a repeated run is averaged
    ]
    out = summary(rows)
    by_name = {p["name"]: p for p in out["presets"]}
    assert by_name["standard"]["seconds"] == 300 and by_name["standard"]["scenes"] == ["indoor"]
    assert by_name["high"]["seconds"] == 1100 and by_name["high"]["fscore_1pct"] == 0.6
    assert [p["name"] for p in out["presets"]] == ["standard", "high"]
    assert out["pareto"] is False  # F-score 0.6 is not above standard's 0.6 + 0.01


def test_pareto_needs_both_figures_better_on_every_machine() -> None:
    rows = [
        _row("preview", "indoor", 100, 0.40, 25.0, "cpu"),
        _row("preview", "indoor", 50, 0.40, 25.0),
        _row("standard", "indoor", 300, 0.50, 31.0),
    ]
    assert summary(rows)["pareto"] is True  # the CPU ran one preset: nothing to compare there
    rows.append(_row("high", "indoor", 900, 0.55, 31.05))  # PSNR gain below 0.1 dB
    assert summary(rows)["pareto"] is False


def test_by_range_splits_the_score_by_distance_to_the_cameras() -> None:
    import numpy as np

    from benchmarks.tradeoff import by_range

    rng = np.random.default_rng(0)
    # the seen surface: 100 points at 0.2 extents from the camera, 300 at 1.5, 600 at 3 (extent 10 m)
    directions = rng.normal(size=(1000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radius = np.repeat([2.0, 15.0, 30.0], [100, 300, 600])
    gt = directions * radius[:, None]
    # the mesh: the near points exactly, the middle ones 1 m off (beyond the 0.1 m tolerance), nothing far
    pred = np.concatenate([gt[:100], gt[100:400] * (16.0 / 15.0)])
    bands = {b["band"]: b for b in by_range(pred, gt, np.zeros((1, 3)), 10.0, 0.1)}
    assert list(bands) == ["0-0.5", "0.5-1", "1-2", "2-inf"]
    assert [bands[k]["seen_share"] for k in bands] == [0.1, 0.0, 0.3, 0.6]
    assert bands["0-0.5"]["recall"] == 1.0 and bands["0-0.5"]["precision"] == 1.0
    assert bands["1-2"]["recall"] == 0.0 and bands["1-2"]["precision"] == 0.0 and bands["1-2"]["mesh_share"] == 0.75
    assert bands["2-inf"]["recall"] == 0.0 and np.isnan(bands["2-inf"]["precision"])  # no mesh there
    assert np.isnan(bands["0.5-1"]["recall"])
