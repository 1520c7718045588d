"""What the user's words name appears in the procedural world: parsing, placement, labels.

Ground truth is the renderer's depth (exact ray-cast camera z) and the camera maths: labelled pixels are lifted
into the world with their depth and the path's poses, so where the content stands is measured, not read back
from the placement code.
"""

from __future__ import annotations

import numpy as np
import pytest

from wonderverse.camera import camera_centers, move_path
from wonderverse.video.content import (
    VOCABULARY,
    WorldContent,
    label_share,
    parse_content,
    segment_words,
)
from wonderverse.video.procedural import ProceduralVideo
from wonderverse.video.prompts import segment_prompt

OUTDOOR = "a quiet village with houses and trees"
INDOOR = "a cozy living room with a sofa"
W, H, T = 128, 96, 6
CLEAN = {"fault_probability": 0.0}


def video(scene: str = OUTDOOR, seed: int = 3) -> ProceduralVideo:
    return ProceduralVideo(scene, seed, W, H, 60.0, CLEAN)


def turn(start: np.ndarray, yaw_deg: float, n: int = T) -> np.ndarray:
    """A planner-like turn (+ left) with the planner's default travel: 0.5 m forward, 0.04 m sideways per degree."""
    return move_path(start, np.radians(yaw_deg), 0.0, 0.5, 0.04 * yaw_deg, n)


def lifted(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """World points (n,3) of the pixels `mask` of a camera-z depth map seen from W2C pose w2c (centres at +0.5)."""
    v, u = np.nonzero(mask)
    z = depth[v, u].astype(np.float64)
    cam = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0] * z, (v + 0.5 - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]


def left_of(start: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Signed angle (degrees, + left) of points (n,3) about the start camera, from its level view direction."""
    f = start[2, :3].copy()
    f[2] = 0.0
    c = camera_centers(start[None])[0]
    d = points[:, :2] - c[:2]
    return np.degrees(np.arctan2(f[0] * d[:, 1] - f[1] * d[:, 0], d @ f[:2]))


# ---------------------------------------------------------------- words


def test_words_name_what_the_world_can_place() -> None:
    lake = parse_content("a frozen lake on the left")
    assert [(i.kind, i.variant, i.count) for i in lake.items] == [("lake", "frozen", 1)]
    assert lake.items[0].name == "lake (frozen)" and lake.side == "left" and not lake.notes
    pines = parse_content("add some pine trees to the right")
    assert [(i.kind, i.variant) for i in pines.items] == [("trees", "pine")] and pines.side == "right"
    assert pines.items[0].count == VOCABULARY["trees"].group_count > 1  # a plural is a group
    tower = parse_content("a tall tower beyond the hills")
    assert [i.kind for i in tower.items] == ["tower"] and tower.items[0].scale > 1 and tower.distance == "far"
    assert [i.kind for i in parse_content("a wooden table").items] == ["table"]
    assert parse_content("turn right and add a lake on the left").side == "left"  # where the content goes
    assert [(i.kind, i.count) for i in parse_content("three houses and two boulders").items] == [
        ("house", 3),
        ("rocks", 2),
    ]
    assert [(i.kind, i.count) for i in parse_content("snowmen and benches").items] == [("snowman", 3), ("bench", 3)]
    assert parse_content("bookshelves").items[0].kind == "shelf"  # -ves plural
    assert parse_content("a pond on the right, frozen").items[0].name == "lake (frozen)"  # variant after its noun
    assert parse_content("a christmas tree").items[0].variant == "pine"


def test_unknown_words_and_references_place_nothing_and_say_so() -> None:
    unicorn = parse_content("a unicorn on the left")
    assert unicorn.items == () and unicorn.side == "left"
    assert len(unicorn.notes) == 1 and "nothing the procedural world can place" in unicorn.notes[0]
    assert "lake" in unicorn.notes[0]  # the note lists what it knows
    assert parse_content("turn left 30 degrees").items == ()
    ref = parse_content("a frozen lake beyond the trees")  # "the trees" are already there
    assert [i.kind for i in ref.items] == ["lake"] and any("'the trees'" in n for n in ref.notes)


def test_the_users_words_come_from_the_end_of_the_segment_prompt() -> None:
    prompt = segment_prompt(OUTDOOR, "left", "a frozen lake on the left")
    assert segment_words(prompt, OUTDOOR) == "a frozen lake on the left"
    assert segment_words(segment_prompt(OUTDOOR, "left", ""), OUTDOOR) == ""  # the scene's own words place nothing
    assert segment_words("a tower", OUTDOOR) == "a tower"  # a bare prompt is all words


# ---------------------------------------------------------------- placement and labels


@pytest.fixture(scope="module")
def lake_run() -> dict:
    """A 40 degree left turn asked for with "a frozen lake on the left", then a second segment (no words) that
    turns a little further from where the first ended, and the same first segment without the words."""
    v = video()
    start = v.world.start_pose()
    path = turn(start, 40.0)
    first = v.generate(segment_prompt(OUTDOOR, "left", "a frozen lake on the left"), path, 1, None)
    second_path = turn(path[-1], 15.0)
    second = v.generate(segment_prompt(OUTDOOR, "left", ""), second_path, 2, first.frames[-1])
    plain = video().generate(segment_prompt(OUTDOOR, "left", ""), path, 1, None)
    return {"video": v, "start": start, "path": path, "first": first, "second": second, "second_path": second_path,
            "plain": plain}  # fmt: skip


def test_a_frozen_lake_appears_on_the_left(lake_run: dict) -> None:
    vid = lake_run["first"]
    gt = vid.gt
    assert gt.labels is not None and gt.labels.shape == (T, H, W) and gt.labels.dtype == np.int16
    assert gt.label_names == {0: "lake (frozen)"}
    share = label_share(gt.labels, gt.label_names, "lake", slice(T - 2, T))
    assert share > 0.02, share
    lake = gt.labels[-1] == 0
    points = lifted(gt.depth[-1], lake, vid.K, gt.poses[-1])
    angle = left_of(lake_run["start"], points)
    assert np.median(angle) > 15.0, np.median(angle)  # well left of where the scene started looking
    assert (np.abs(points[:, 2] - np.median(points[:, 2])) < 0.02).mean() > 0.95  # a flat surface: a lake
    rgb = vid.frames[-1][lake].astype(float).mean(axis=0)
    assert rgb[2] > rgb[0] and rgb.mean() > 120, rgb  # pale blue: ice, not grass
    assert np.isfinite(gt.depth[gt.labels >= 0]).all()  # labels agree with depth


def test_without_the_words_there_is_no_lake(lake_run: dict) -> None:
    plain = lake_run["plain"]
    assert plain.gt.labels is None and plain.gt.label_names == {}
    differs = np.abs(plain.frames[-1].astype(int) - lake_run["first"].frames[-1].astype(int)).max(axis=-1) > 30
    assert differs[lake_run["first"].gt.labels[-1] == 0].mean() > 0.9  # the lake's pixels showed something else


def test_a_later_segment_looking_there_still_sees_the_lake(lake_run: dict) -> None:
    first, second = lake_run["first"], lake_run["second"]
    assert second.gt.label_names == {0: "lake (frozen)"}
    assert label_share(second.gt.labels, second.gt.label_names, "lake", slice(T - 2, T)) > 0.01
    before = lifted(first.gt.depth[-1], first.gt.labels[-1] == 0, first.K, first.gt.poses[-1])
    after = lifted(second.gt.depth[-1], second.gt.labels[-1] == 0, second.K, second.gt.poses[-1])
    assert abs(np.median(after[:, 2]) - np.median(before[:, 2])) < 0.02  # the same water level
    # the same lake: the points seen now lie among those seen before (within a few cell sizes)
    gap = np.linalg.norm(after[:, None, :2] - before[None, ::7, :2], axis=-1).min(axis=1)
    assert np.median(gap) < 1.0
    assert len(lake_run["video"].content.placements) == 1  # no words: nothing new placed


def test_same_words_and_seed_give_the_same_frames(lake_run: dict) -> None:
    v = video()
    again = v.generate(segment_prompt(OUTDOOR, "left", "a frozen lake on the left"), lake_run["path"], 1, None)
    assert np.array_equal(again.frames, lake_run["first"].frames)
    assert np.array_equal(again.gt.labels, lake_run["first"].gt.labels)
    v.generate(segment_prompt(OUTDOOR, "left", "a frozen lake on the left"), lake_run["path"], 5, None)
    assert len(v.content.placements) == 1  # a retry of the segment places nothing twice


def test_a_table_on_the_right_stands_on_the_floor_indoors() -> None:
    v = video(INDOOR)
    assert v.world.kind == "indoor"
    start = v.world.start_pose()
    vid = v.generate(segment_prompt(INDOOR, "right", "a table on the right"), turn(start, -35.0), 1, None)
    gt = vid.gt
    assert gt.label_names == {0: "table"}
    table = gt.labels[-1] == 0
    assert table.mean() > 0.01
    points = lifted(gt.depth[-1], table, vid.K, gt.poses[-1])
    assert points[:, 2].min() < 0.1 and points[:, 2].max() < 1.6  # legs on the floor (z = 0), table height
    assert np.median(left_of(start, points)) < -10.0  # right of where the room was first seen
    assert np.isfinite(gt.depth[gt.labels >= 0]).all()


def test_placement_depends_only_on_seed_words_and_end_pose() -> None:
    """Content placed before (a tower elsewhere) does not move a later lake; a lake does not fit indoors."""
    v = video()
    start = v.world.start_pose()
    K, size = v.K, (W, H)
    alone, after = WorldContent(), WorldContent()
    end = turn(start, 40.0)[-1]
    after.add(v.world, "a tall tower on the right", turn(start, -40.0)[-1], K, size, 3)
    for content in (alone, after):
        content.add(v.world, "a frozen lake on the left", end, K, size, 3)
    assert [p.name for p in after.placements] == ["tower", "lake (frozen)"]
    assert np.array_equal(alone.placements[0].centre, after.placements[1].centre)
    indoor = video(INDOOR)
    room = WorldContent()
    room.add(indoor.world, "a frozen lake", indoor.world.start_pose(), K, size, 3)
    assert room.placements == [] and room.world is None
    assert any("does not fit" in n for n in room.notes)


def test_a_fresh_video_model_replays_the_words_of_earlier_segments(lake_run: dict) -> None:
    """A later step or `extend` builds a new video model: `replay_content` gives it the stored segments' words, so
    the next segment still sees the lake (and an unguided backend without a world is left alone)."""
    from wonderverse.video.prompts import replay_content

    fresh = video()
    replay_content(
        fresh,
        OUTDOOR,
        [("left", "a frozen lake on the left", lake_run["path"]), ("right", "", turn(lake_run["start"], -20.0))],
    )
    second = fresh.generate(segment_prompt(OUTDOOR, "left", ""), lake_run["second_path"], 2, None)
    assert second.gt.label_names == {0: "lake (frozen)"}
    assert np.array_equal(second.gt.labels, lake_run["second"].gt.labels)
    replay_content(object(), OUTDOOR, [("left", "a frozen lake on the left", lake_run["path"])])  # no world: no-op


@pytest.mark.parametrize("words", ["further ahead, a row of lanterns", "further ahead, a statue", "a house ahead"])
def test_what_is_placed_ahead_leaves_the_way_ahead_open(words: str) -> None:
    """A segment's words place content in front of its end; the next segments go on forward from there. Their
    camera must never come inside what was placed (it would film the inside of a lamp: frames nothing registers),
    measured by the renderer: along a forward move past everything placed, no labelled pixel is nearer than 1 m."""
    v = ProceduralVideo(OUTDOOR, 5, 64, 48, 60.0, CLEAN)
    start = v.world.start_pose()
    first = v.generate(segment_prompt(OUTDOOR, "forward", words), move_path(start, 0.0, 0.0, 2.0, 0.0, 4), 1, None)
    assert first.gt.labels is not None and (first.gt.labels[-1] >= 0).mean() > 0.003  # the content is in view
    on = v.generate(
        segment_prompt(OUTDOOR, "forward", ""), move_path(first.gt.poses[-1], 0.0, 0.0, 30.0, 0.0, 24), 2, None
    )
    labelled = on.gt.labels >= 0
    assert labelled.any()  # still passed on the way
    assert on.gt.depth[labelled].min() > 1.0, on.gt.depth[labelled].min()
