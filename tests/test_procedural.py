"""The procedural video model: worlds, ray-cast frames, exact ground truth and injected faults.

Ground truth comes from the world itself (its mesh, its palette, the camera maths of
`wonderverse.camera`), never from the renderer's own outputs compared with themselves.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from wonderverse.camera import camera_centers, intrinsics, look_at
from wonderverse.video.procedural import (
    ProceduralOptions,
    ProceduralVideo,
    apply_pose_fault,
    demo_path,
    draw_fault,
    render_view,
)
from wonderverse.video.world import MATERIAL_IDS, WorldParams, build_world, classify_prompt

OUTDOOR = "a quiet village with houses and trees"
INDOOR = "a cozy living room with a sofa"
CLEAN = {"fault_probability": 0.0}
W, H = 96, 64


def video(prompt: str = OUTDOOR, width: int = W, height: int = H, **opts: object) -> ProceduralVideo:
    return ProceduralVideo(prompt, 3, width, height, 60.0, {**CLEAN, **opts})


def back_project(depth: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """World points (n,3) of the finite pixels of a depth map (camera z) seen from W2C pose w2c,
    pixel centres at +0.5, in row-major order."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    ok = np.isfinite(depth)
    z = depth[ok].astype(np.float64)
    cam = np.stack([(u[ok] - K[0, 2]) / K[0, 0] * z, (v[ok] - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    R, t = w2c[:3, :3], w2c[:3, 3]
    return (cam - t) @ R  # R^T (x - t), row-wise


# ---------------------------------------------------------------- worlds


def test_prompt_words_pick_kind_theme_and_layout() -> None:
    assert classify_prompt("a cozy living room")[:3] == ("indoor", "living_room", "living_room")
    assert classify_prompt("the kitchen of an old farmhouse")[0] == "indoor"
    assert classify_prompt("a mushroom forest")[0] == "outdoor"  # "room" inside a word is no room
    assert classify_prompt("a snowy christmas village at night") == ("outdoor", "christmas", "meadow", True)
    assert classify_prompt("an autumn forest")[1:3] == ("autumn", "forest")
    assert classify_prompt("a cozy living room", world="outdoor")[0] == "outdoor"


def test_same_prompt_and_seed_give_the_same_world_and_a_new_seed_another() -> None:
    a, b, c = build_world(OUTDOOR, 5), build_world(OUTDOOR, 5), build_world(OUTDOOR, 6)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.tri_material, b.tri_material)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)
    assert np.array_equal(a.start_pose(), b.start_pose())


def test_outdoor_world_surrounds_a_clear_zone_and_the_camera_starts_above_ground() -> None:
    p = WorldParams()
    world = build_world(OUTDOOR, 0)
    assert world.kind == "outdoor" and world.theme == "meadow"
    ground = world.tri_object == 0
    ext = np.abs(world.vertices[world.triangles[ground]].reshape(-1, 3)[:, :2]).max()
    assert ext == pytest.approx(p.terrain_radius_m, abs=1.0)
    obj = world.vertices[world.vert_object > 0]
    radial = np.hypot(obj[:, 0], obj[:, 1])
    assert radial.min() >= p.clear_radius_m
    pivots = np.array([o.pivot for o in world.objects])
    sectors = np.floor((np.arctan2(pivots[:, 1], pivots[:, 0]) + np.pi) / (np.pi / 4)).astype(int) % 8
    assert set(sectors) == set(range(8)), "objects all the way round the origin"
    kinds = {o.kind for o in world.objects}
    assert {"house", "tree", "rock"} <= kinds
    start = world.start_pose()
    centre = camera_centers(start[None])[0]
    forward = start[2, :3]
    assert forward[1] > 0.9 and -0.5 < forward[2] < -0.05, "looking towards +y, slightly down"
    below = world_ray_hit(world, centre, np.array([0.0, 0.0, -1.0]))
    assert below == pytest.approx(p.camera_height_m, abs=0.05)


def world_ray_hit(world, origin: np.ndarray, direction: np.ndarray) -> float:
    import open3d as o3d

    ray = np.concatenate([origin, direction]).astype(np.float32)[None]
    return float(world.scene.cast_rays(o3d.core.Tensor(ray))["t_hit"].numpy()[0])


def test_indoor_world_is_a_closed_room_with_furniture_and_a_centred_camera() -> None:
    p = WorldParams()
    world = build_world(INDOOR, 0)
    assert world.kind == "indoor" and world.layout == "living_room"
    sx, sy, sz = p.room_size_m
    lim = np.array([sx / 2, sy / 2, sz]) + p.wall_thickness_m + 1e-3
    assert (np.abs(world.vertices[:, :2]) <= lim[:2]).all()
    assert world.vertices[:, 2].min() >= -lim[2] and world.vertices[:, 2].max() <= lim[2]
    assert len(world.objects) >= 10 and "sofa" in {o.kind for o in world.objects}
    centre = camera_centers(world.start_pose()[None])[0]
    assert centre == pytest.approx([0.0, 0.0, p.indoor_camera_height_m])
    for d in ([1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]):  # closed: every ray hits
        assert np.isfinite(world_ray_hit(world, centre, np.array(d, dtype=float)))


def test_theme_words_change_the_palette_and_the_rendered_ground() -> None:
    green, snow = video("a green meadow"), video("a snowy winter meadow")
    gid = MATERIAL_IDS["ground"]
    assert snow.world.colors_b[gid].mean() > green.world.colors_b[gid].mean() + 0.2
    assert green.world.colors_b[gid][1] > green.world.colors_b[gid][0]  # grass is green
    low_g = green.render(green.world.start_pose())[0][H // 2 :].reshape(-1, 3).astype(float).mean(axis=0)
    low_s = snow.render(snow.world.start_pose())[0][H // 2 :].reshape(-1, 3).astype(float).mean(axis=0)
    assert low_s.mean() > low_g.mean() + 40, "snow on the ground is brighter than grass"
    assert low_g[1] > low_g[2], "grass reflects more green than blue"


# ---------------------------------------------------------------- frames


def test_same_inputs_give_identical_frames_and_ground_truth() -> None:
    a, b = video(), video()
    path = demo_path(a.world.start_pose(), 3)
    va, vb = a.generate("x", path, 1, None), b.generate("y", path, 1, None)
    assert va.frames.dtype == np.uint8 and va.frames.shape == (3, H, W, 3)
    assert np.array_equal(va.frames, vb.frames)
    assert np.array_equal(va.gt.depth, vb.gt.depth) and np.array_equal(va.gt.normals, vb.gt.normals)
    assert np.array_equal(va.K, intrinsics(W, H, 60.0)) and va.gt.faults == {}
    assert va.frames.std() > 20, "a textured image, not a flat fill"


@pytest.mark.parametrize("prompt", [OUTDOOR, INDOOR])
def test_textures_give_plenty_of_sift_features(prompt: str) -> None:
    import pycolmap

    extractor = pycolmap.FeatureExtractor.create(pycolmap.FeatureExtractionOptions())
    v = video(prompt, 320, 208)
    frames = v.generate("", demo_path(v.world.start_pose(), 4), 0, None).frames
    grey = (frames.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)).astype(np.uint8)
    counts = [len(extractor.extract_from_uint8_array(np.ascontiguousarray(g))[0]) for g in grey]
    assert min(counts) >= 300, counts


def test_depth_is_consistent_between_views() -> None:
    """Back-project frame 0's depth, re-project into frame 1: it lands on frame 1's depth."""
    v = video(width=160, height=112)
    path = demo_path(v.world.start_pose(), 2, yaw_deg=8.0, forward_m=0.6)
    vid = v.generate("", path, 0, None)
    K, (d0, d1) = vid.K, vid.gt.depth
    pts = back_project(d0, K, vid.gt.poses[0])
    cam1 = pts @ vid.gt.poses[1][:3, :3].T + vid.gt.poses[1][:3, 3]
    z = cam1[:, 2]
    u, v_ = K[0, 0] * cam1[:, 0] / z + K[0, 2] - 0.5, K[1, 1] * cam1[:, 1] / z + K[1, 2] - 0.5
    inside = (u >= 0) & (v_ >= 0) & (u < d1.shape[1] - 1) & (v_ < d1.shape[0] - 1) & (z > 0)
    u, v_, z = u[inside], v_[inside], z[inside]
    i0, j0 = np.floor(v_).astype(int), np.floor(u).astype(int)
    fu, fv = u - j0, v_ - i0
    inv = 1.0 / d1  # inverse depth is linear across a plane's image: interpolate that
    corners = np.stack([inv[i0, j0], inv[i0, j0 + 1], inv[i0 + 1, j0], inv[i0 + 1, j0 + 1]])
    smooth = (corners.min(axis=0) > 0) & (corners.max(axis=0) < corners.min(axis=0) * 1.02)
    interp = ((1 - fu) * (1 - fv) * corners[0] + fu * (1 - fv) * corners[1] + (1 - fu) * fv * corners[2]
              + fu * fv * corners[3])  # fmt: skip
    z_seen = 1.0 / interp[smooth]
    rel = (z[smooth] - z_seen) / z_seen
    assert smooth.sum() > 0.3 * d0.size
    assert np.mean(np.abs(rel) < 0.01) > 0.95, "most points match frame 1's depth within 1%"
    assert np.mean(rel < -0.01) < 0.01, "no point lies in front of what frame 1 sees"


def test_normals_are_unit_face_the_camera_and_agree_with_the_depth() -> None:
    v = video(width=128, height=96)
    _, depth, normals = v.render(v.world.start_pose())
    hit = np.isfinite(depth)
    assert hit.mean() > 0.5
    assert np.allclose(np.linalg.norm(normals[hit], axis=-1), 1.0, atol=1e-4)
    K = v.K
    u, vv = np.meshgrid(np.arange(128) + 0.5, np.arange(96) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    assert (np.einsum("hwc,hwc->hw", normals, rays)[hit] < 0).all()
    # normals from the depth map's own geometry (cross product of neighbouring camera points)
    cam = rays * np.where(hit, depth, 0.0)[..., None]
    du, dv = cam[1:-1, 2:] - cam[1:-1, :-2], cam[2:, 1:-1] - cam[:-2, 1:-1]
    n_depth = np.cross(du, dv)
    n_depth /= np.maximum(np.linalg.norm(n_depth, axis=-1, keepdims=True), 1e-12)
    inner = normals[1:-1, 1:-1]
    ok = hit[1:-1, 1:-1] & hit[1:-1, 2:] & hit[1:-1, :-2] & hit[2:, 1:-1] & hit[:-2, 1:-1]
    cos = np.abs(np.einsum("hwc,hwc->hw", n_depth, inner))[ok]
    assert np.mean(cos > np.cos(np.radians(5))) > 0.8, "depth-derived normals agree away from edges"


def test_sky_has_infinite_depth_zero_normals_and_sky_colours() -> None:
    v = video()
    start = v.world.start_pose()
    eye = camera_centers(start[None])[0]
    up = look_at(eye, eye + np.array([0.0, 1.0, 0.6]))  # looking up over the horizon
    rgb, depth, normals = v.render(up)
    sky = ~np.isfinite(depth)
    assert sky[: H // 4].mean() > 0.9 and (depth[~sky] > 0).all()
    assert np.isposinf(depth[sky]).all() and (normals[sky] == 0).all()
    top = rgb[:4].reshape(-1, 3).astype(float).mean(axis=0)
    assert top[2] > top[0], "daylight sky is bluer than red"


def test_a_path_starting_at_the_last_pose_continues_the_last_frame_exactly() -> None:
    v = video()
    first = demo_path(v.world.start_pose(), 4, yaw_deg=20.0)
    a = v.generate("", first, 0, None)
    second = demo_path(first[-1], 3, yaw_deg=15.0, forward_m=1.0)
    b = v.generate("", second, 1, a.frames[-1])
    assert np.array_equal(b.frames[0], a.frames[-1])
    assert np.array_equal(b.gt.depth[0], a.gt.depth[-1])


def test_shadow_maps_agree_with_shadow_rays() -> None:
    """The fast shadow-map lookup against the exact reference: one shadow ray per pixel."""
    fast, exact = video(width=160, height=112), video(width=160, height=112, shadow_method="rays")
    pose = demo_path(fast.world.start_pose(), 2, yaw_deg=40.0)[1]
    a, b = fast.render(pose)[0].astype(int), exact.render(pose)[0].astype(int)
    close = np.abs(a - b).max(axis=-1) <= 12
    assert close.mean() > 0.93, close.mean()
    flat = video(width=160, height=112, shadows=False).render(pose)[0].astype(int)
    assert np.mean((flat - b).max(axis=-1) > 20) > 0.02, "shadows darken part of the image"


@settings(max_examples=8, deadline=None)
@given(
    yaw=st.floats(-180, 180), pitch=st.floats(-30, 30), dx=st.floats(-2, 2), dy=st.floats(-2, 2),
    indoor=st.booleans(),
)  # fmt: skip
def test_any_view_has_positive_depth_and_unit_facing_normals(
    yaw: float, pitch: float, dx: float, dy: float, indoor: bool
) -> None:
    world = build_world(INDOOR if indoor else OUTDOOR, 3)
    eye = camera_centers(world.start_pose()[None])[0] + [dx, dy, 0.0]
    a, p = np.radians(yaw), np.radians(pitch)
    w2c = look_at(eye, eye + np.array([np.cos(p) * np.sin(a), np.cos(p) * np.cos(a), np.sin(p)]))
    K = intrinsics(32, 24, 60.0)
    _, depth, normals = render_view(world, K, w2c, 32, 24, ProceduralOptions(**CLEAN))
    hit = np.isfinite(depth)
    assert (depth[hit] > 0).all() and np.isposinf(depth[~hit]).all()
    assert np.allclose(np.linalg.norm(normals[hit], axis=-1), 1.0, atol=1e-4)
    assert (normals[~hit] == 0).all()
    u, v = np.meshgrid(np.arange(32) + 0.5, np.arange(24) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    assert (np.einsum("hwc,hwc->hw", normals, rays)[hit] < 0).all()
    if indoor:
        assert hit.all(), "a closed room has no sky"


# ---------------------------------------------------------------- faults

T = 8


def clean_and_faulty(kind: str) -> tuple[ProceduralVideo, np.ndarray, object, object]:
    v = video(width=64, height=48)
    path = demo_path(v.world.start_pose(), T, yaw_deg=20.0, forward_m=1.0)
    clean = v.generate("", path, 0, None)
    bad = video(width=64, height=48, force_fault=kind).generate("", path, 0, None)
    return v, path, clean, bad


def test_teleport_moves_the_camera_centre_by_its_magnitude_from_frame_k() -> None:
    _, path, clean, bad = clean_and_faulty("teleport")
    f = bad.gt.faults
    k = f["frames"][0]
    assert f["type"] == "teleport" and f["frames"] == [k] and T // 4 <= k < T
    jump = camera_centers(bad.gt.poses) - camera_centers(path)
    assert np.allclose(jump[:k], 0.0)
    assert np.allclose(np.linalg.norm(jump[k:], axis=1), f["magnitude"])
    assert 0.8 <= f["magnitude"] <= 2.5
    assert np.array_equal(bad.frames[:k], clean.frames[:k]) and not np.array_equal(bad.frames[k], clean.frames[k])


def test_rotation_turns_the_camera_suddenly_and_keeps_its_centre() -> None:
    _, path, clean, bad = clean_and_faulty("rotation")
    f = bad.gt.faults
    k = f["frames"][0]
    rel = bad.gt.poses[k, :3, :3] @ path[k, :3, :3].T
    angle = np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1)))
    assert f["type"] == "rotation" and angle == pytest.approx(f["magnitude"], abs=1e-6)
    assert 9.0 <= angle <= 26.0
    assert np.allclose(camera_centers(bad.gt.poses), camera_centers(path))
    assert np.allclose(bad.gt.poses[:k], path[:k]) and np.array_equal(bad.frames[:k], clean.frames[:k])


def test_morph_moves_objects_in_view_from_frame_k() -> None:
    v, path, clean, bad = clean_and_faulty("morph")
    f = bad.gt.faults
    k = f["frames"][0]
    assert f["type"] == "morph" and f["objects"] and len(f["scales"]) == len(f["objects"])
    assert np.allclose(bad.gt.poses, path), "the camera follows the path"
    assert np.array_equal(bad.frames[:k], clean.frames[:k])
    changed = [not np.array_equal(bad.gt.depth[i], clean.gt.depth[i]) for i in range(k, T)]
    assert any(changed)
    kinds = {v.world.objects[i - 1].kind for i in f["objects"]}
    assert kinds and all(kind != "ground" for kind in kinds)


def test_freeze_repeats_frame_k_and_records_the_repeated_pose() -> None:
    _, path, clean, bad = clean_and_faulty("freeze")
    f = bad.gt.faults
    frames = f["frames"]
    k, n = frames[0], len(frames)
    assert f["type"] == "freeze" and n == min(5, T) and frames == list(range(k, k + n))
    for i in frames:
        assert np.array_equal(bad.frames[i], clean.frames[k]) and np.allclose(bad.gt.poses[i], path[k])
    after = k + n
    if after < T:
        assert np.array_equal(bad.frames[after], clean.frames[after])


def test_fault_rate_matches_the_configured_probability() -> None:
    opts = ProceduralOptions(fault_probability=0.2)
    faults = [draw_fault(3, seed, 25, opts) for seed in range(200)]
    n = sum(f is not None for f in faults)
    # binomial(200, 0.2): mean 40, sd 5.7; 4 sd either side
    assert 17 <= n <= 63, n
    assert {f.type for f in faults if f} == {"teleport", "rotation", "morph", "freeze"}
    assert all(f is None for f in (draw_fault(3, s, 25, ProceduralOptions(fault_probability=0)) for s in range(50)))
    assert all(draw_fault(3, s, 25, ProceduralOptions(fault_probability=1)) for s in range(50))


def test_a_new_seed_gives_an_independent_draw() -> None:
    opts = ProceduralOptions(fault_probability=0.5)
    draws = np.array([draw_fault(7, seed, 25, opts) is not None for seed in range(400)])
    assert draw_fault(7, 11, 25, opts) == draw_fault(7, 11, 25, opts)
    agree = np.mean(draws[1:] == draws[:-1])  # consecutive seeds: a coin flip each
    assert 0.4 < agree < 0.6, agree
    other_scene = np.array([draw_fault(8, seed, 25, opts) is not None for seed in range(400)])
    assert 0.4 < np.mean(other_scene == draws) < 0.6


def test_pose_faults_leave_a_clean_path_alone() -> None:
    path = demo_path(build_world(OUTDOOR, 0).start_pose(), 5)
    poses, record = apply_pose_fault(path, None, ProceduralOptions())
    assert np.array_equal(poses, path) and record == {}


# ---------------------------------------------------------------- bad inputs


def test_bad_inputs_are_refused_with_clear_messages() -> None:
    v = video()
    path = demo_path(v.world.start_pose(), 3)
    with pytest.raises(ValueError, match="reference frame has shape"):
        v.generate("", path, 0, np.zeros((H + 1, W, 3), np.uint8))
    nan = path.copy()
    nan[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r"NaN/inf entries at frames \[1\]"):
        v.generate("", nan, 0, None)
    with pytest.raises(ValueError, match="0 frames"):
        v.generate("", np.zeros((0, 4, 4)), 0, None)
    with pytest.raises(ValueError, match=r"shape \(T, 4, 4\)"):
        v.generate("", path[:, :3], 0, None)
    skew = path.copy()
    skew[0, :3, :3] *= 2.0
    with pytest.raises(ValueError, match="not proper rotations"):
        v.generate("", skew, 0, None)
    with pytest.raises(ValueError, match="seed must be >= 0"):
        v.generate("", path, -1, None)
    with pytest.raises(ValidationError):
        ProceduralVideo(OUTDOOR, 0, W, H, 60.0, {"no_such_option": 1})
    with pytest.raises(ValidationError, match="lower bound"):
        ProceduralOptions(teleport_m=(3.0, 1.0))
    with pytest.raises(ValueError, match="at least 2 frames"):
        video(force_fault="freeze").generate("", path[:1], 0, None)
