"""What the user's words name, placed into a procedural world where the new segment looks.

Words: `parse_content("a frozen lake on the left")` finds the things the procedural world can place
(`VOCABULARY`: lake, trees, tower, house, rocks, snowman, fountain, statue, table, bench, lamp, bush, car, and
indoors sofa, bed, shelf, plant, box, wardrobe), with their variant ("frozen", "pine", "palm"), how many ("some
pine trees", "three houses", "a forest") and size ("a tall tower"), plus the side ("on the left"; else the first
left or right) and distance ("beyond", "nearby") the words give.

Placement: `place_content` puts each item in front of the segment path's last pose, at the kind's preferred
distance (times 1.6 for "beyond", 0.6 for "near"), aimed a little towards the named side, on the terrain or the
floor, inside the world (skyline rim, dry land, room walls), choosing among candidate spots the one least
overlapping the world's objects and least hidden or off screen. A lake carves the ground under it and displaces
the world's objects standing in it.

Rules (what a test or a benchmark may rely on):
- A placement depends only on (scene seed, words, the path's end pose) and the scene's own world, never on
  content placed earlier: a segment's content is the same whatever its siblings asked for, and in whatever order
  they were generated.
- Nouns after "the" (also this, that, these, those, your, its) refer to what is already there ("beyond the
  trees") and place nothing; an unknown noun places nothing. Both leave a note in words (`WorldContent.notes`).
- Persistence: `WorldContent` (one per `ProceduralVideo`) keeps everything placed into its world, in arrival
  order: content placed for one generation is part of the world for that generation and every later call of the
  same video model (a later segment that looks at the lake sees it; a retry of the segment places nothing twice).
  A fresh video model (another process) knows only the words it has been given.
- Labels: label id = arrival order (0, 1, ...); names are `Placement.name`, "kind" or "kind (variant)".
"""

from __future__ import annotations

import hashlib
import re
import threading
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from wonderverse.video.world import (
    MeshBuilder,
    World,
    WorldObject,
    _bench,
    _bush,
    _car,
    _conifer,
    _Ctx,
    _house,
    _indoor_item,
    _lamp,
    _palm,
    _place,
    _rock,
    _snowman,
    _tree,
    blob,
    box,
    frustum,
)

if TYPE_CHECKING:
    from collections.abc import Callable, Iterable

WorldKind = Literal["outdoor", "indoor"]
Side = Literal["left", "right"]


@dataclass(frozen=True)
class ContentKind:
    """One thing the procedural world can place from words.

    nouns: singular nouns naming it (plurals are recognised by rule: +s, +es, -man/-men, -f/-ves); noun_variants:
    nouns that also say the variant ("pines": trees, pine); group_nouns: nouns that mean many at once, with their
    count ("forest": 9); variants: adjectives (or nouns used as adjectives) -> variant; worlds: where it fits;
    radius_m: footprint radius of one instance; distance_m: preferred distance from the camera outdoors and
    indoor_distance_m indoors; group_count: instances for a plural without a number; probe_height_m: height
    above the ground at which its visibility is probed.
    """

    nouns: tuple[str, ...]
    worlds: tuple[WorldKind, ...]
    radius_m: float
    distance_m: float
    indoor_distance_m: float = 3.0
    variants: dict[str, str] = field(default_factory=dict)
    noun_variants: dict[str, str] = field(default_factory=dict)
    group_nouns: dict[str, int] = field(default_factory=dict)
    group_count: int = 3
    probe_height_m: float = 1.0


_PINE = dict.fromkeys(("pine", "fir", "spruce", "evergreen", "coniferous", "conifer", "christmas", "xmas"), "pine")
_PALM = dict.fromkeys(("palm", "tropical", "coconut"), "palm")
_LEAFY = dict.fromkeys(("oak", "maple", "birch", "willow", "beech", "leafy", "deciduous", "apple"), "broadleaf")
_FROZEN = dict.fromkeys(("frozen", "icy", "ice", "iced", "icebound", "glacial", "freezing"), "frozen")

VOCABULARY: dict[str, ContentKind] = {
    "lake": ContentKind(
        ("lake", "pond", "lagoon", "pool", "mere", "tarn"),
        ("outdoor",),
        radius_m=5.0,
        distance_m=13.0,
        variants=_FROZEN,
        group_count=1,
        probe_height_m=0.05,
    ),
    "trees": ContentKind(
        (
            "tree",
            "forest",
            "woodland",
            "woods",
            "grove",
            "orchard",
            "pine",
            "fir",
            "spruce",
            "conifer",
            "evergreen",
            "palm",
            "oak",
            "maple",
            "birch",
            "willow",
            "beech",
        ),
        ("outdoor", "indoor"),
        radius_m=2.8,
        distance_m=14.0,
        variants=_PINE | _PALM | _LEAFY,
        noun_variants=_PINE | _PALM | _LEAFY,
        group_nouns={"forest": 9, "woodland": 9, "woods": 9, "grove": 6, "orchard": 6},
        group_count=5,
        probe_height_m=2.5,
    ),
    "tower": ContentKind(
        ("tower", "spire", "turret", "lighthouse", "belfry", "minaret"),
        ("outdoor",),
        radius_m=3.0,
        distance_m=24.0,
        variants={"stone": "stone", "brick": "brick"},
        group_count=2,
        probe_height_m=4.0,
    ),
    "house": ContentKind(
        ("house", "cottage", "cabin", "hut", "barn", "farmhouse", "chalet", "shed"),
        ("outdoor",),
        radius_m=4.8,
        distance_m=18.0,
        group_count=3,
        probe_height_m=2.0,
    ),
    "rocks": ContentKind(
        ("rock", "boulder", "stone"), ("outdoor",), radius_m=1.4, distance_m=9.0, group_count=4, probe_height_m=0.4
    ),
    "snowman": ContentKind(("snowman",), ("outdoor",), radius_m=0.7, distance_m=6.0, group_count=3),
    "fountain": ContentKind(
        ("fountain",),
        ("outdoor", "indoor"),
        radius_m=2.5,
        distance_m=7.0,
        indoor_distance_m=4.0,
        group_count=2,
        probe_height_m=0.8,
    ),
    "statue": ContentKind(
        ("statue", "sculpture", "monument"), ("outdoor", "indoor"), radius_m=0.9, distance_m=8.0, group_count=3
    ),
    "table": ContentKind(
        ("table", "desk"), ("outdoor", "indoor"), radius_m=1.1, distance_m=6.0, group_count=2, probe_height_m=0.6
    ),
    "bench": ContentKind(("bench",), ("outdoor",), radius_m=1.0, distance_m=6.0, probe_height_m=0.5),
    "lamp": ContentKind(
        ("lamp", "streetlight", "streetlamp", "lamppost", "lantern"),
        ("outdoor", "indoor"),
        radius_m=0.5,
        distance_m=6.0,
        probe_height_m=1.2,
    ),
    "bush": ContentKind(("bush", "shrub", "hedge"), ("outdoor",), radius_m=1.3, distance_m=8.0, probe_height_m=0.5),
    "car": ContentKind(("car",), ("outdoor",), radius_m=2.3, distance_m=10.0, group_count=2, probe_height_m=0.8),
    "sofa": ContentKind(
        ("sofa", "couch"), ("indoor",), radius_m=1.3, distance_m=3.0, group_count=2, probe_height_m=0.5
    ),
    "bed": ContentKind(("bed",), ("indoor",), radius_m=1.4, distance_m=3.5, group_count=2, probe_height_m=0.5),
    "shelf": ContentKind(("shelf", "bookshelf", "bookcase"), ("indoor",), radius_m=1.0, distance_m=3.0, group_count=2),
    "plant": ContentKind(("plant", "houseplant"), ("indoor",), radius_m=0.4, distance_m=2.5, probe_height_m=0.5),
    "box": ContentKind(("box", "crate"), ("indoor",), radius_m=0.5, distance_m=2.5, probe_height_m=0.3),
    "wardrobe": ContentKind(("wardrobe", "cupboard", "closet"), ("indoor",), radius_m=1.0, distance_m=3.0),
}

# Words that change what follows them.
DEFINITE = frozenset(("the", "this", "that", "these", "those", "your", "its", "their", "our", "my"))
INDEFINITE = {"a": 1, "an": 1, "one": 1, "another": 1, "single": 1}
NUMBERS = {"two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8, "nine": 9, "ten": 10,
           "couple": 2, "pair": 2, "few": 3, "several": 4, "many": 8, "lots": 8, "dozen": 12}  # fmt: skip
SIZE_WORDS = {"tall": 1.4, "big": 1.4, "large": 1.4, "high": 1.4, "huge": 1.7, "giant": 1.7, "enormous": 1.7,
              "towering": 1.7, "small": 0.7, "little": 0.7, "tiny": 0.5, "short": 0.7, "low": 0.7}  # fmt: skip
FAR_WORDS = frozenset(("beyond", "far", "distant", "distance", "horizon", "faraway", "afar", "yonder"))
NEAR_WORDS = frozenset(("near", "nearby", "close", "closer", "next", "beside", "foreground"))
BOUNDARY = frozenset((",", ".", ";", "and", "with", "or", "on", "to", "at", "in", "into", "near", "by", "beyond",
                      "behind", "past", "of", "across", "over", "under", "towards", "toward", "between", "from",
                      "where", "which"))  # fmt: skip


class ContentParams(BaseModel):
    """How content is placed (metres, shares of the horizontal half field of view, cost weights)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    far_factor: float = Field(1.6, gt=1, description="preferred distance times this for 'beyond', 'distant'")
    near_factor: float = Field(0.6, gt=0, lt=1, description="preferred distance times this for 'near', 'close'")
    side_bias_share: float = Field(0.3, ge=0, le=1, description="'on the left': aim this share of the half FOV left")
    bearing_jitter_share: float = Field(0.08, ge=0, description="random aim offset, share of the half FOV")
    distance_jitter_share: float = Field(0.1, ge=0, lt=1, description="random share of the preferred distance")
    max_bearing_share: float = Field(0.75, gt=0, le=1, description="candidates stay within this share of half FOV")
    bearing_steps: int = Field(9, ge=1, description="candidate bearings across the view")
    distance_factors: tuple[float, ...] = Field(
        (0.6, 0.75, 0.9, 1.0, 1.15, 1.35, 1.6), min_length=1, description="candidate distances, of the preferred"
    )
    camera_clearance_m: float = Field(1.5, ge=0, description="content keeps this far from the camera outdoors")
    indoor_camera_clearance_m: float = Field(1.0, ge=0)
    object_gap_m: float = Field(0.4, ge=0, description="free space kept to the world's objects")
    way_ahead_weight: float = Field(
        4.0,
        ge=0,
        description="cost per footprint radius of intrusion into the way ahead (the camera's clearance "
        "either side of its heading, from the camera on): a later forward move does not fly into what was placed",
    )
    rim_margin_m: float = Field(3.0, ge=0, description="outdoors: stay this far inside the skyline rim")
    wall_margin_m: float = Field(0.15, ge=0, description="indoors: stay this far from the walls")
    overlap_weight: float = Field(4.0, ge=0, description="cost per footprint radius of overlap with objects")
    lake_overlap_share: float = Field(
        0.25, ge=0, le=1, description="a lake displaces the objects inside it: its overlap costs this share"
    )
    occlusion_weight: float = Field(8.0, ge=0, description="cost of all probes hidden behind something")
    off_screen_weight: float = Field(8.0, ge=0, description="cost of all probes outside the end frame")
    group_near_share: float = Field(
        0.8, gt=0, le=1, description="a group's nearest instances stay about this share of the kind's distance away"
    )
    distance_weight: float = Field(1.0, ge=0, description="cost per relative departure from the preferred distance")
    bearing_weight: float = Field(0.5, ge=0, description="cost per half FOV of departure from the aimed bearing")
    lake_relief_weight: float = Field(1.0, ge=0, description="cost per metre of ground relief under a lake")
    group_spacing: float = Field(1.1, gt=0, description="instances of a group keep this many radii apart")
    instance_tries: int = Field(40, ge=1, description="rejection-sampling tries per instance of a group")
    max_count: int = Field(12, ge=1, description="at most this many instances of one item")
    lake_segments: int = Field(40, ge=8, description="shoreline vertices of a lake")
    lake_shore_jitter: float = Field(0.12, ge=0, lt=0.5, description="relative wobble of the shoreline radius")
    lake_level_above_m: float = Field(0.02, ge=0, description="water level above the lowest ground on the shore")
    lake_carve_depth_m: float = Field(0.4, gt=0, description="the ground inside the shore sinks this far under it")


# ---------------------------------------------------------------- words


@dataclass(frozen=True)
class ContentItem:
    """One thing the words name: its kind (a `VOCABULARY` key), variant ("frozen", "pine", or None), how many
    instances, size factor (1 = usual), and the phrase it came from."""

    kind: str
    variant: str | None
    count: int
    scale: float
    phrase: str

    @property
    def name(self) -> str:
        """The item's name: its kind and variant, e.g. "lake (frozen)", "trees (pine)", "tower"."""
        return f"{self.kind} ({self.variant})" if self.variant else self.kind


@dataclass(frozen=True)
class ContentRequest:
    """What words ask to place: items, the side ("on the left") and distance ("beyond": far) they give, and
    notes in words about what was not understood or not placed."""

    words: str
    items: tuple[ContentItem, ...]
    side: Side | None = None
    distance: Literal["near", "far"] | None = None
    notes: tuple[str, ...] = ()


_NOUNS: dict[str, str] = {n: kind for kind, spec in VOCABULARY.items() for n in spec.nouns}
_TOKEN = re.compile(r"[a-z]+|\d+|[,.;]")
_SIDE = re.compile(r"(?<![a-z])(left|right)(?![a-z])")
_POSITIONAL_SIDE = re.compile(r"(?<![a-z])(?:on|to|at|towards?)\s+(?:the\s+|your\s+)?(left|right)(?![a-z])")


def _singular(word: str) -> tuple[str, bool] | None:
    """(singular noun of the vocabulary, was plural) for a word, or None."""
    if word in _NOUNS:
        return word, word.endswith("s") and word[:-1] in _NOUNS  # "woods" is its own noun
    for suffix, repl in (("s", ""), ("es", ""), ("men", "man"), ("ves", "f"), ("ves", "fe")):
        if word.endswith(suffix) and word[: -len(suffix)] + repl in _NOUNS:
            return word[: -len(suffix)] + repl, True
    return None


def parse_content(words: str, params: ContentParams | None = None) -> ContentRequest:
    """The things `words` name that the procedural world can place (see the module docstring for the rules).

    A noun phrase is read left to right: a determiner ("a", "some", "three", "the"), adjectives (size words,
    variants such as "frozen" or "pine"; a vocabulary noun right before another noun is an adjective: "pine
    trees", "stone tower"), then the noun. Plurals place `group_count` instances unless a number says how many.
    """
    p = params or ContentParams()
    tokens = _TOKEN.findall(words.lower())
    items: list[ContentItem] = []
    notes: list[str] = []
    mods: list[str] = []
    det: str | None = None
    start = 0
    for i, tok in enumerate(tokens):
        noun = _singular(tok)
        nxt = tokens[i + 1] if i + 1 < len(tokens) else ""
        if noun is not None and _singular(nxt) is None:
            base, plural = noun
            kind = _NOUNS[base]
            spec = VOCABULARY[kind]
            phrase = " ".join(tokens[start : i + 1])
            if det in DEFINITE:
                notes.append(f"{phrase!r} refers to what is already there; nothing placed for it")
            else:
                variant = spec.noun_variants.get(base)
                for m in mods:
                    variant = spec.variants.get(m, variant)
                count = spec.group_nouns.get(base, 0)
                number = next((n for n in (_count(m) for m in [det or "", *mods]) if n), 0)
                if number:
                    count = max(count, number) if count else number
                elif not count:
                    count = spec.group_count if plural or det in ("some", "more") else 1
                scale = float(np.prod([SIZE_WORDS[m] for m in mods if m in SIZE_WORDS]))
                items.append(ContentItem(kind, variant, min(count, p.max_count), scale, phrase))
            mods, det, start = [], None, i + 1
        elif tok in BOUNDARY:
            mods, det, start = [], None, i + 1
        elif tok in DEFINITE or tok in INDEFINITE or tok in ("some", "more"):
            det, mods = tok, []
            start = i
        elif (
            items
            and items[-1].variant is None
            and tok in VOCABULARY[items[-1].kind].variants
            and not _noun_ahead(tokens, i)
        ):  # "a pond on the right, frozen": a variant after its noun
            items[-1] = replace(items[-1], variant=VOCABULARY[items[-1].kind].variants[tok])
        else:
            mods.append(tok)
    side_match = _POSITIONAL_SIDE.search(words.lower()) or _SIDE.search(words.lower())  # "on the left" first
    side: Side | None = side_match[1] if side_match else None  # type: ignore[assignment]
    distance: Literal["near", "far"] | None = None
    if any(t in FAR_WORDS for t in tokens):
        distance = "far"
    elif any(t in NEAR_WORDS for t in tokens):
        distance = "near"
    if not items and words.strip():
        notes.append(
            f"nothing the procedural world can place is named in {words.strip()!r}; it knows: " + ", ".join(VOCABULARY)
        )
    return ContentRequest(words, tuple(items), side, distance, tuple(notes))


def _noun_ahead(tokens: list[str], i: int) -> bool:
    """Whether a vocabulary noun follows token i before the clause ends (".", ";", "and", "with", "or")."""
    for tok in tokens[i + 1 :]:
        if tok in (".", ";", "and", "with", "or"):
            return False
        if _singular(tok) is not None:
            return True
    return False


def _count(word: str) -> int:
    if word.isdigit():
        return int(word)
    return NUMBERS.get(word, 0)


def segment_words(prompt: str, scene_prompt: str) -> str:
    """The user's words in a segment's prompt: what follows the scene prompt ("... displaying {scene prompt}.
    {words}.", `wonderverse.video.prompts.segment_prompt`), or the whole prompt when the scene prompt is not in it
    (the scene's own words never place content a second time)."""
    norm = " ".join(prompt.split())
    scene = " ".join(scene_prompt.split())
    at = norm.lower().rfind(scene.lower()) if scene else -1
    if at < 0:
        return norm.strip()
    return norm[at + len(scene) :].strip(" .,;")


# ---------------------------------------------------------------- placement


@dataclass
class Placement:
    """One item placed into a world: its centre (x, y, ground z) in native metres, footprint radius, the mesh of
    its instances (`MeshBuilder` arrays with local object ids 1..k, 0 for ground-like fill that carries no
    label) and their objects, the key that makes it unique, and notes."""

    item: ContentItem
    key: str
    centre: np.ndarray
    radius_m: float
    arrays: tuple[np.ndarray, ...]
    objects: list[WorldObject]
    notes: tuple[str, ...] = ()
    shore: Shore | None = None

    @property
    def name(self) -> str:
        return self.item.name


class _Transformed(MeshBuilder):
    """A MeshBuilder that scales every part about the origin, then moves it to `offset` (an instance is built at
    the origin by world.py's builders and lands where the placement puts it, at its size)."""

    def __init__(self) -> None:
        super().__init__()
        self.offset = np.zeros(3)
        self.scale = 1.0

    def add(self, mesh: tuple[np.ndarray, np.ndarray], material: str, obj: int = 0) -> None:
        v, f = mesh
        super().add((np.asarray(v, dtype=np.float64) * self.scale + self.offset, f), material, obj)


def _seed(scene_seed: int, words: str, index: int, end_w2c: np.ndarray) -> tuple[np.random.SeedSequence, str]:
    """Seed sequence and hex key of one item: sha256 of the scene seed, the normalised words, the item's index
    and the end pose rounded to 1e-5 (so float noise in the path does not move the content)."""
    norm = " ".join(words.lower().split())
    pose = np.round(np.asarray(end_w2c, dtype=np.float64)[:3, :4], 5) + 0.0  # +0.0: no negative zeros
    digest = hashlib.sha256(f"{scene_seed}|{norm}|{index}|".encode() + pose.tobytes()).digest()
    ints = [int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)]
    return np.random.SeedSequence(ints), digest.hex()[:16]


def _ground(world: World) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Ground height z(x, y) in native metres: the terrain outdoors, the floor (0) indoors."""
    terrain = world.terrain
    if world.kind == "outdoor" and terrain is not None:
        return lambda x, y: np.asarray(terrain.height(x, y), dtype=np.float64)
    return lambda x, y: np.zeros(np.broadcast(np.asarray(x), np.asarray(y)).shape)


def _in_bounds(world: World, xy: np.ndarray, radius: float, p: ContentParams) -> bool:
    """Whether a footprint of `radius` around xy lies in the world: inside the room's walls, or inside the
    skyline rim and (beach) on dry land."""
    wp = world.params
    if world.kind == "indoor":
        sx, sy, _ = wp.room_size_m
        return bool(abs(xy[0]) + radius <= sx / 2 - p.wall_margin_m and abs(xy[1]) + radius <= sy / 2 - p.wall_margin_m)
    if np.hypot(xy[0], xy[1]) + radius > wp.rim_start_m - p.rim_margin_m:
        return False
    terrain = world.terrain
    if terrain is None or terrain.sea_dir is None:
        return True
    a = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = xy[:, None] + radius * np.stack([np.cos(a), np.sin(a)])
    return all(terrain.is_dry(float(x), float(y)) for x, y in [xy, *ring.T])


def _visible_share(world: World, centre: np.ndarray, w2c: np.ndarray, K: np.ndarray, size: tuple[int, int],
                   probes: np.ndarray) -> tuple[float, float]:  # fmt: skip
    """(share of probes (n,3) hidden behind the world's surfaces seen from the camera centre, share projecting
    outside the frame of width x height) for a W2C pose `w2c` (native metres)."""
    import open3d as o3d

    d = probes - centre
    rays = np.concatenate([np.broadcast_to(centre, d.shape), d], axis=1).astype(np.float32)
    t = world.scene.cast_rays(o3d.core.Tensor(rays), nthreads=1)["t_hit"].numpy()
    hidden = float(np.mean(t < 0.97))
    cam = probes @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * cam[:, 0] / z + K[0, 2]
        v = K[1, 1] * cam[:, 1] / z + K[1, 2]
    inside = (z > 0.1) & (u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1])
    return hidden, float(1.0 - inside.mean())


def _probes(
    kind: str, xy: np.ndarray, radius: float, height: float, ground: Callable, across: np.ndarray
) -> np.ndarray:
    """Points (5,3) whose visibility stands for the item's: its centre and four points half its radius away
    (across the view and along it), `height` above the ground (a lake: at its level)."""
    along = np.array([-across[1], across[0]])
    pts = [xy, xy + across * radius / 2, xy - across * radius / 2, xy + along * radius / 2, xy - along * radius / 2]
    out = np.array([[x, y, float(ground(x, y)) + height] for x, y in pts])
    if kind == "lake":
        out[:, 2] = out[:, 2].max()
    return out


def _relief(ground: Callable, xy: np.ndarray, radius: float) -> tuple[float, float]:
    """(lowest, highest) ground under a disc of `radius` around xy, sampled every half metre and on its rim."""
    n = max(3, int(np.ceil(2 * radius / 0.5)) + 1)
    g = np.linspace(-radius, radius, n)
    gx, gy = np.meshgrid(g, g)
    keep = gx**2 + gy**2 <= radius**2
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    xs = np.concatenate([gx[keep], radius * np.cos(a)]) + xy[0]
    ys = np.concatenate([gy[keep], radius * np.sin(a)]) + xy[1]
    z = ground(xs, ys)
    return float(z.min()), float(z.max())


def _instance_radius(world: World, item: ContentItem) -> float:
    """Footprint radius of one instance: the kind's, times the size words (instances are scaled as a whole)."""
    r = 0.8 if item.kind == "trees" and world.kind == "indoor" else VOCABULARY[item.kind].radius_m
    return r * item.scale


def _group_radius(r: float, count: int, spacing: float) -> float:
    """Radius of a disc holding `count` discs of radius `spacing` * r at a packing density of 0.6."""
    return r if count <= 1 else max(r, spacing * r * float(np.sqrt(count / 0.6)))


def place_content(
    world: World,
    request: ContentRequest,
    end_w2c: np.ndarray,
    K: np.ndarray,
    size: tuple[int, int],
    scene_seed: int,
    params: ContentParams | None = None,
) -> list[Placement]:
    """Place every item of `request` in front of a camera at `end_w2c` (W2C, native metres: the path's last pose)
    with intrinsics K and frame size (width, height), deterministically from (scene_seed, words, end pose).

    Each item's anchor is chosen among candidates spread over distances and bearings of the view: the one of
    least cost (overlap with the world's objects and earlier items of the same request, probes hidden or off
    screen, distance from the preferred one, bearing from the aimed one, ground relief under a lake), inside the
    world; then its instances are spread over a disc around it. Items that do not fit the world's kind (a lake
    indoors) are skipped with a note. Returns one Placement per placed item."""
    p = params or ContentParams()
    ground = _ground(world)
    R = np.asarray(end_w2c, dtype=np.float64)[:3, :3]
    centre = -R.T @ np.asarray(end_w2c, dtype=np.float64)[:3, 3]
    f = R[2].copy()
    f[2] = 0.0
    if np.linalg.norm(f) < 1e-9:  # looking straight down or up: forward is the camera's up or down on screen
        f = -R[1].copy() if R[2, 2] < 0 else R[1].copy()
        f[2] = 0.0
    heading = f[:2] / np.linalg.norm(f[:2])
    half_fov = float(np.arctan(size[0] / 2 / K[0, 0]))
    obstacles = [(np.array(o.pivot[:2]), o.radius_m) for o in world.objects if o.kind not in ("painting",)]
    indoor = world.kind == "indoor"
    clear = p.indoor_camera_clearance_m if indoor else p.camera_clearance_m
    camera = _Camera(centre[:2], heading, clear)
    placed: list[Placement] = []
    for index, item in enumerate(request.items):
        spec = VOCABULARY[item.kind]
        if world.kind not in spec.worlds:
            note = f"a {item.kind} does not fit in an {world.kind} world; {item.phrase!r} not placed"
            placed.append(Placement(item, "", np.zeros(3), 0.0, (), [], (note,)))
            continue
        seq, key = _seed(scene_seed, request.words, index, end_w2c)
        rng = np.random.default_rng(seq)
        r_inst = _instance_radius(world, item)
        radius = _group_radius(r_inst, item.count, p.group_spacing)
        d_pref = (spec.indoor_distance_m if indoor else spec.distance_m) * {"far": p.far_factor, "near": p.near_factor,
                                                                            None: 1.0}[request.distance]  # fmt: skip
        near = p.group_near_share * d_pref if item.count > 1 else 0.0  # a group's front row stays this far away
        d_min = max(radius + clear, radius - r_inst + near)
        d_pref = max(d_pref * (1.0 + p.distance_jitter_share * rng.uniform(-1, 1)), d_min + 0.5)
        aim = {"left": 1.0, "right": -1.0, None: 0.0}[request.side] * p.side_bias_share
        aim = (aim + p.bearing_jitter_share * rng.uniform(-1, 1)) * half_fov
        best: tuple[float, np.ndarray] | None = None
        bearings = np.linspace(-1, 1, p.bearing_steps) * p.max_bearing_share * half_fov if p.bearing_steps > 1 else [0]
        for dist_f in p.distance_factors:
            d = max(d_pref * dist_f, d_min)
            for b in bearings:
                direction = np.array(
                    [np.cos(b) * heading[0] - np.sin(b) * heading[1], np.sin(b) * heading[0] + np.cos(b) * heading[1]]
                )
                xy = centre[:2] + d * direction
                if not _in_bounds(world, xy, radius, p):
                    continue
                overlap = sum(
                    max(0.0, r + radius + p.object_gap_m - float(np.linalg.norm(xy - q))) for q, r in obstacles
                )
                ahead = 0.0 if item.kind == "lake" else camera.in_way_ahead(xy, radius)
                across = np.array([-direction[1], direction[0]])
                probes = _probes(item.kind, xy, radius, spec.probe_height_m * max(item.scale, 1.0), ground, across)
                hidden, off = _visible_share(world, centre, end_w2c, K, size, probes)
                cost = (
                    p.overlap_weight * overlap / radius * (p.lake_overlap_share if item.kind == "lake" else 1.0)
                    + p.occlusion_weight * hidden
                    + p.off_screen_weight * off
                    + p.distance_weight * abs(d - d_pref) / d_pref
                    + p.bearing_weight * abs(b - aim) / half_fov
                    + p.way_ahead_weight * ahead / radius
                )
                if item.kind == "lake":
                    lo, hi = _relief(ground, xy, radius)
                    cost += p.lake_relief_weight * (hi - lo)
                if best is None or cost < best[0]:
                    best = (cost, xy)
        notes: list[str] = []
        if best is None:  # nothing in view fits inside the world: the nearest spot straight ahead that does
            d = d_min
            xy = centre[:2] + d * heading
            notes.append(f"no room for {item.phrase!r} in view; placed {d:.1f} m ahead")
        else:
            xy = best[1]
        placement = _build_item(world, item, key, xy, r_inst, radius, camera, near, rng, obstacles, p)
        placement.notes = (*placement.notes, *notes)
        placed.append(placement)
        obstacles.append((xy, radius))
    return placed


def _build_item(
    world: World,
    item: ContentItem,
    key: str,
    xy: np.ndarray,
    r_inst: float,
    radius: float,
    camera: _Camera,
    near: float,
    rng: np.random.Generator,
    obstacles: list[tuple[np.ndarray, float]],
    p: ContentParams,
) -> Placement:
    """The item's mesh: one instance at xy, or `count` spread over the disc of `radius` around it, each on the
    ground, clear of the obstacles, of each other, of the camera (by `near`) and of its way ahead where the tries
    allow."""
    ground = _ground(world)
    b = _Transformed()
    c = _Ctx(b, rng, world.params, world.theme, world.night)
    spots: list[np.ndarray] = []
    shore = None
    for _ in range(item.count):
        if item.count == 1:
            spots.append(xy)
            continue
        best: tuple[float, np.ndarray] | None = None
        for _try in range(p.instance_tries):
            a, r = rng.uniform(0, 2 * np.pi), (radius - r_inst) * np.sqrt(rng.uniform())
            q = xy + r * np.array([np.cos(a), np.sin(a)])
            if not _in_bounds(world, q, r_inst, p):
                continue
            clash = sum(max(0.0, p.group_spacing * r_inst * 2 - float(np.linalg.norm(q - s))) for s in spots)
            clash += sum(max(0.0, r_inst + ro - float(np.linalg.norm(q - o))) for o, ro in obstacles)
            clash += max(0.0, near - float(np.linalg.norm(q - camera.xy)))
            clash += camera.in_way_ahead(q, r_inst)
            if best is None or clash < best[0]:
                best = (clash, q)
            if clash == 0:
                break
        if best is not None:
            spots.append(best[1])
    facing = float(np.arctan2(-camera.heading[0], camera.heading[1]))  # local +y (an item's back) away from the camera
    for q in spots:
        z = float(ground(q[0], q[1]))
        b.offset, b.scale = np.array([q[0], q[1], z]), item.scale
        obj = b.new_object(_object_kind(item, world), (float(q[0]), float(q[1]), z), r_inst)
        if item.kind == "lake":
            b.scale = 1.0
            shore = _lake(c, obj, q, r_inst, item.variant == "frozen", ground, p)
        else:
            _instance(c, item, world.kind, obj, facing + rng.uniform(-0.3, 0.3))
    centre = np.array([xy[0], xy[1], float(ground(xy[0], xy[1]))])
    return Placement(item, key, centre, radius, b.arrays() if b.verts else (), b.objects, shore=shore)


@dataclass(frozen=True)
class _Camera:
    """The camera content is placed for: its ground position, horizontal heading (unit) and the clearance kept
    either side of its way ahead."""

    xy: np.ndarray
    heading: np.ndarray
    clear: float

    def in_way_ahead(self, xy: np.ndarray, radius: float) -> float:
        """How far (metres) a disc at xy of `radius` reaches into the way ahead: the band of `clear` either side
        of the ray from the camera along its heading. A forward move continues along that ray, so what stands in
        the band is what a later segment would fly into; 0 for a disc beside or behind the camera."""
        rel = np.asarray(xy, dtype=np.float64) - self.xy
        if float(rel @ self.heading) + radius <= 0:
            return 0.0
        across = abs(float(rel[0] * self.heading[1] - rel[1] * self.heading[0]))
        return max(0.0, self.clear + radius - across)


def _object_kind(item: ContentItem, world: World) -> str:
    if item.kind == "trees":
        return {"pine": "conifer", "palm": "palm"}.get(
            item.variant or "", "conifer" if world.kind == "indoor" else "tree"
        )
    return item.kind


def _instance(c: _Ctx, item: ContentItem, world_kind: str, obj: int, yaw: float) -> None:
    """One instance of the item, built at the origin (the builder moves and scales it)."""
    rng, kind, origin = c.rng, item.kind, np.zeros(3)
    if kind == "trees":
        if world_kind == "indoor":
            _conifer(c, origin, obj, rng.uniform(2.0, 2.5))
        elif item.variant == "palm":
            _palm(c, origin, obj, rng.uniform(5, 8))
        elif item.variant == "pine" or (item.variant is None and rng.random() < 0.4):
            _conifer(c, origin, obj, rng.uniform(5, 10))
        else:
            _tree(c, origin, obj, rng.uniform(5, 9))
    elif kind == "house":
        _house(c, origin, yaw, obj, np.array([rng.uniform(5, 7.5), rng.uniform(4, 6), rng.uniform(2.8, 3.8)]))
    elif kind == "rocks":
        _rock(c, origin, obj, rng.uniform(0.6, 1.3))
    elif kind == "snowman":
        _snowman(c, origin, obj)
    elif kind == "bench":
        _bench(c, origin, yaw, obj)
    elif kind == "lamp" and world_kind == "outdoor":
        _lamp(c, origin, obj, rng.uniform(3.5, 4.5))
    elif kind == "bush":
        _bush(c, origin, obj, rng.uniform(0.6, 1.1))
    elif kind == "car":
        _car(c, origin, yaw, obj)
    elif kind == "tower":
        _tower(c, obj, rng.uniform(11, 16), "brick" if item.variant == "brick" else "rock")
    elif kind == "fountain":
        _fountain(c, obj, "ice" if c.wintry else "water")
    elif kind == "statue":
        _statue(c, obj)
    else:  # furniture: table, lamp indoors, sofa, bed, shelf, plant, box, wardrobe
        _, build = _indoor_item(c, kind)
        build(origin, yaw, obj)


def _tower(c: _Ctx, obj: int, height: float, wall: str) -> None:
    """A round stone tower: shaft, parapet, conical roof, a few windows; `height` to the parapet."""
    r = c.rng.uniform(1.8, 2.4)
    c.b.add(_place(frustum(r * 1.1, r, height + 0.5, c.seg), (0, 0, -0.5)), wall, obj)
    c.b.add(_place(frustum(r * 1.25, r * 1.25, 1.2, c.seg), (0, 0, height)), wall, obj)
    c.b.add(_place(frustum(r * 1.35, 0.0, r * 1.8, c.seg), (0, 0, height + 1.2)), "roof", obj)
    window = "light" if c.night else "glass"
    for k in range(4):
        a = c.rng.uniform(0, 2 * np.pi)
        z = height * (0.3 + 0.18 * k)
        c.b.add(_place(box((0.2, 0.6, 1.0)), (r * np.cos(a), r * np.sin(a), z), a), window, obj)


def _fountain(c: _Ctx, obj: int, water: str) -> None:
    """A round basin with water, a column and an upper bowl."""
    r, seg = c.rng.uniform(1.8, 2.3), c.seg * 2
    c.b.add(_place(frustum(r, r, 0.75, seg), (0, 0, -0.4)), "marble", obj)
    c.b.add(_place(frustum(r, r, 0.3, seg, caps=False), (0, 0, 0.35)), "marble", obj)
    c.b.add(_place(frustum(r - 0.12, r - 0.12, 0.03, seg), (0, 0, 0.35)), water, obj)
    c.b.add(frustum(0.3, 0.22, 1.5, seg), "marble", obj)
    c.b.add(_place(frustum(0.25, 0.9, 0.3, seg), (0, 0, 1.4)), "marble", obj)
    c.b.add(_place(frustum(0.82, 0.82, 0.03, seg), (0, 0, 1.69)), water, obj)


def _statue(c: _Ctx, obj: int) -> None:
    """A figure on a plinth."""
    seg = c.seg
    c.b.add(_place(box((1.0, 1.0, 1.6)), (0, 0, 0.4)), "marble", obj)
    for sx in (-0.15, 0.15):
        c.b.add(_place(frustum(0.12, 0.1, 0.9, seg), (sx, 0, 1.2)), "metal", obj)
    c.b.add(_place(frustum(0.3, 0.36, 0.8, seg), (0, 0, 2.1)), "metal", obj)
    c.b.add(_place(blob(0.17, c.rng, 0.05), (0, 0, 3.1)), "metal", obj)


@dataclass(frozen=True)
class Shore:
    """A lake's shoreline: centre xy (native metres), mean radius, relative wobble, wave phases (3,), water level
    (world z) and how deep the ground under it is carved (`carve_depth_m` below the level)."""

    centre: tuple[float, float]
    radius_m: float
    jitter: float
    phases: tuple[float, float, float]
    level: float
    carve_depth_m: float

    def radius_at(self, angle: np.ndarray) -> np.ndarray:
        """Shore radius (metres) in the directions `angle` (radians about +z from +x)."""
        ph = self.phases
        wave = np.sin(2 * angle + ph[0]) + 0.6 * np.sin(3 * angle + ph[1]) + 0.3 * np.sin(5 * angle + ph[2])
        return self.radius_m * (1 + self.jitter * wave / 1.9)

    def inside(self, xy: np.ndarray) -> np.ndarray:
        """(n,) bool: which points xy (n,2) lie inside the shore."""
        d = np.asarray(xy, dtype=np.float64) - self.centre
        return np.hypot(d[:, 0], d[:, 1]) < self.radius_at(np.arctan2(d[:, 1], d[:, 0]))


def _lake(c: _Ctx, obj: int, xy: np.ndarray, radius: float, frozen: bool, ground: Callable, p: ContentParams) -> Shore:
    """A lake around xy: a flat water (or ice) surface inside a wobbly shore, at the lowest ground on the shore,
    with a bank from there down to the ground (object 0: no label; it closes the gap where the ground outside
    falls below the water). Built relative to the builder's offset (the ground under xy). Returns the shore: the
    ground inside it is carved below the water when the lake joins the world (`add_content`)."""
    n = p.lake_segments
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ph = c.rng.uniform(0, 2 * np.pi, 3)
    shore = Shore((float(xy[0]), float(xy[1])), radius, p.lake_shore_jitter, tuple(ph), 0.0, p.lake_carve_depth_m)
    ring = shore.radius_at(a)
    xs, ys = xy[0] + ring * np.cos(a), xy[1] + ring * np.sin(a)
    base = float(ground(xy[0], xy[1]))
    ground_ring = ground(xs, ys)
    level = float(ground_ring.min()) + p.lake_level_above_m
    rel = np.column_stack([xs - xy[0], ys - xy[1]])
    top = np.vstack([[0.0, 0.0, level - base], np.column_stack([rel, np.full(n, level - base)])])
    i = np.arange(n)
    j = (i + 1) % n
    c.b.add((top, np.column_stack([np.zeros(n, dtype=np.int64), 1 + i, 1 + j])), "ice" if frozen else "water", obj)
    bank = np.vstack(
        [np.column_stack([rel, np.full(n, level - base)]), np.column_stack([rel, ground_ring - base - 0.3])]
    )
    quads = np.vstack([np.column_stack([i, j, n + j]), np.column_stack([i, n + j, n + i])])
    c.b.add((bank, quads), "ground", 0)
    return replace(shore, level=level)


# ---------------------------------------------------------------- the world with its content


def add_content(base: World, placements: list[Placement]) -> tuple[World, np.ndarray]:
    """The base world with every placement's mesh appended, the ground under each lake carved below its water and
    the world's own objects standing in a lake (pivot inside its shore) taken away (their triangles; their
    `objects` entries stay, so object ids do not change). A new World: its ray-casting scene and caches are
    rebuilt. Also returns object_label (n_objects+1,) int16: for each
    object id the index in `placements` of the item it belongs to, -1 for the world's own objects and the static
    shell (object 0)."""
    verts, tris, mats, tri_obj, vert_obj, parts = [base.vertices], [base.triangles], [base.tri_material], [
        base.tri_object], [base.vert_object], [base.tri_part]  # fmt: skip
    objects = list(base.objects)
    labels = [-1] * (len(objects) + 1)
    n_verts, n_parts = len(base.vertices), int(base.tri_part.max()) + 1
    for index, pl in enumerate(placements):
        if not pl.arrays:
            continue
        v, f, m, to, vo, pa = pl.arrays
        shift = len(objects)
        verts.append(v)
        tris.append(f + n_verts)
        mats.append(m)
        tri_obj.append(np.where(to > 0, to + shift, 0).astype(np.int32))
        vert_obj.append(np.where(vo > 0, vo + shift, 0).astype(np.int32))
        parts.append(pa + n_parts)
        for o in pl.objects:
            objects.append(WorldObject(o.id + shift, o.kind, o.pivot, o.radius_m))
            labels.append(index)
        n_verts += len(v)
        n_parts += int(pa.max()) + 1
    vertices = np.vstack(verts).astype(np.float32)
    tri_object = np.concatenate(tri_obj).astype(np.int32)
    shell = np.flatnonzero(base.vert_object == 0)
    gone = np.zeros(len(objects) + 1, dtype=bool)  # the world's own objects a lake displaced
    pivots = np.array([o.pivot[:2] for o in base.objects]).reshape(-1, 2)
    for pl in placements:  # a lake's ground sinks under its water; what stood there goes
        if pl.shore is not None:
            sunk = shell[pl.shore.inside(base.vertices[shell, :2])]
            floor = np.float32(pl.shore.level - pl.shore.carve_depth_m)
            vertices[sunk, 2] = np.minimum(vertices[sunk, 2], floor)
            gone[1 : len(base.objects) + 1] |= pl.shore.inside(pivots)
    keep = ~gone.take(tri_object)
    world = replace(
        base,
        vertices=vertices,
        triangles=np.vstack(tris).astype(np.int32)[keep],
        tri_material=np.concatenate(mats).astype(np.int32)[keep],
        tri_object=tri_object[keep],
        vert_object=np.concatenate(vert_obj).astype(np.int32),
        tri_part=np.concatenate(parts).astype(np.int32)[keep],
        objects=objects,
        _scene=None,
        cache={},
    )
    return world, np.array(labels, dtype=np.int16)


class WorldContent:
    """Everything the words have placed into one world, in arrival order (label id = index), and the world that
    holds it (None until something is placed). Safe to share between threads; pickles without its lock."""

    def __init__(self, params: ContentParams | None = None) -> None:
        self.params = params or ContentParams()
        self.placements: list[Placement] = []
        self.notes: list[str] = []
        self.world: World | None = None
        self.object_label = np.full(1, -1, dtype=np.int16)
        self._keys: set[str] = set()
        self._lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        del state["_lock"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def add(
        self,
        base: World,
        words: str,
        end_w2c: np.ndarray,
        K: np.ndarray,
        size: tuple[int, int],
        scene_seed: int,
    ) -> None:
        """Place what `words` name for a segment ending at `end_w2c` (native metres) into the world (`self.world`
        becomes the base world with all content so far). Words already placed from this end pose place nothing
        again (a retry of the same segment); words naming nothing placeable leave only a note."""
        request = parse_content(words, self.params)
        _, key = _seed(scene_seed, words, -1, end_w2c)
        with self._lock:
            self._note(request.notes)
            if not request.items or key in self._keys:
                return
            self._keys.add(key)
            placed = place_content(base, request, end_w2c, K, size, scene_seed, self.params)
            self._note([n for pl in placed for n in pl.notes])
            new = [pl for pl in placed if pl.arrays]
            if new:
                self.placements.extend(new)
                self.world, self.object_label = add_content(base, self.placements)

    def _note(self, notes: Iterable[str]) -> None:
        self.notes.extend(n for n in notes if n not in self.notes)

    def snapshot(self) -> tuple[World | None, np.ndarray, dict[int, str]]:
        """(world with the content, None before any; object_label (n_objects+1,) int16; label names: id -> the
        item's name, e.g. "lake (frozen)"), all of one moment."""
        with self._lock:
            return self.world, self.object_label, {i: pl.name for i, pl in enumerate(self.placements)}


def label_share(
    labels: np.ndarray | None, label_names: dict[int, str], kind: str, frames: slice = slice(None)
) -> float:
    """Share of the pixels of `labels` (T,H,W) int16 (frames `frames`) showing content of `kind` (a VOCABULARY key:
    its names are "kind" or "kind (variant)"); 0 without labels."""
    if labels is None:
        return 0.0
    ids = [i for i, name in label_names.items() if name.split(" (")[0] == kind]
    sel = labels[frames]
    return float(np.isin(sel, ids).mean()) if ids and sel.size else 0.0
