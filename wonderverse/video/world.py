"""Procedural worlds for the default video model: (prompt, seed) -> a triangle mesh with materials.

The prompt's words pick the kind (outdoor terrain or an indoor room), the theme (palette) and the
layout; the seed and a sha256 of the prompt drive every random choice, so the same inputs always give
the same world. World frame: right-handed, +z up, metres; outdoors the origin lies on the ground
under the camera's start, indoors on the floor at the room's centre.
"""

# ruff: noqa: RUF005  (`pos + [dx, dy, dz]` adds to a numpy array; it is not list concatenation)
from __future__ import annotations

import hashlib
import itertools
import re
from dataclasses import dataclass, field
from enum import IntEnum
from functools import cache
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from wonderverse.camera import look_at
from wonderverse.video.procedural_options import WorldParams

if TYPE_CHECKING:
    import open3d as o3d


class Pattern(IntEnum):
    """Per-material surface patterns the renderer knows (on top of the value noise)."""

    NOISE = 0
    GRASS = 1
    BRICK = 2
    PLANKS = 3
    BARK = 4
    LEAVES = 5
    ROOF = 6
    WATER = 7
    FABRIC = 8
    WALLPAPER = 9
    FACADE = 10
    PAINTING = 11
    EMISSIVE = 12
    TILES = 13


# name: (pattern, feature size in metres, contrast, per-object colour jitter)
MATERIALS: dict[str, tuple[Pattern, float, float, float]] = {
    "ground": (Pattern.GRASS, 1.0, 1.0, 0.0),
    "rock": (Pattern.NOISE, 0.8, 1.0, 0.15),
    "bark": (Pattern.BARK, 0.5, 1.0, 0.1),
    "crown": (Pattern.LEAVES, 0.7, 1.0, 0.2),
    "conifer": (Pattern.LEAVES, 0.5, 1.0, 0.1),
    "brick": (Pattern.BRICK, 1.0, 0.8, 0.15),
    "plaster": (Pattern.NOISE, 0.5, 1.0, 0.25),
    "roof": (Pattern.ROOF, 1.0, 0.8, 0.15),
    "wood": (Pattern.PLANKS, 0.6, 0.8, 0.15),
    "metal": (Pattern.NOISE, 0.3, 0.7, 0.0),
    "light": (Pattern.EMISSIVE, 1.0, 0.0, 0.0),
    "glass": (Pattern.NOISE, 0.6, 0.6, 0.1),
    "water": (Pattern.WATER, 3.0, 0.9, 0.0),
    "facade": (Pattern.FACADE, 0.8, 0.9, 0.3),
    "decor_red": (Pattern.NOISE, 0.2, 0.4, 0.1),
    "decor_gold": (Pattern.NOISE, 0.2, 0.4, 0.1),
    "snow": (Pattern.NOISE, 0.8, 0.4, 0.05),
    "cactus": (Pattern.BARK, 0.4, 0.8, 0.1),
    "fabric": (Pattern.FABRIC, 0.4, 0.8, 0.5),
    "car": (Pattern.NOISE, 0.5, 0.4, 0.7),
    "floor": (Pattern.PLANKS, 0.9, 0.9, 0.0),
    "tile": (Pattern.TILES, 0.5, 0.8, 0.0),
    "wall": (Pattern.WALLPAPER, 0.4, 1.0, 0.0),
    "ceiling": (Pattern.NOISE, 0.6, 0.7, 0.0),
    "rug": (Pattern.FABRIC, 0.5, 1.0, 0.6),
    "books": (Pattern.NOISE, 0.08, 0.8, 0.9),
    "painting": (Pattern.PAINTING, 0.4, 1.0, 1.0),
    "cardboard": (Pattern.NOISE, 0.3, 0.6, 0.2),
    "marble": (Pattern.NOISE, 0.4, 0.9, 0.1),
    "plant": (Pattern.LEAVES, 0.15, 1.0, 0.2),
    "ice": (Pattern.NOISE, 1.5, 0.5, 0.0),  # a frozen lake (video/content.py)
}
MATERIAL_IDS: dict[str, int] = {name: i for i, name in enumerate(MATERIALS)}

Rgb = tuple[float, float, float]
# Two colours per material (dark, light); the texture mixes between them.
BASE_PALETTE: dict[str, tuple[Rgb, Rgb]] = {
    "ground": ((0.20, 0.36, 0.12), (0.50, 0.62, 0.25)),
    "rock": ((0.32, 0.31, 0.30), (0.66, 0.64, 0.60)),
    "bark": ((0.18, 0.12, 0.08), (0.45, 0.34, 0.24)),
    "crown": ((0.10, 0.28, 0.08), (0.42, 0.62, 0.22)),
    "conifer": ((0.04, 0.18, 0.08), (0.20, 0.42, 0.20)),
    "brick": ((0.45, 0.18, 0.12), (0.75, 0.40, 0.28)),
    "plaster": ((0.70, 0.64, 0.52), (0.95, 0.90, 0.80)),
    "roof": ((0.35, 0.10, 0.08), (0.65, 0.28, 0.18)),
    "wood": ((0.30, 0.19, 0.10), (0.62, 0.45, 0.28)),
    "metal": ((0.20, 0.21, 0.23), (0.45, 0.47, 0.50)),
    "light": ((1.00, 0.92, 0.70), (1.00, 0.97, 0.85)),
    "glass": ((0.10, 0.16, 0.22), (0.35, 0.45, 0.55)),
    "water": ((0.05, 0.20, 0.35), (0.30, 0.55, 0.70)),
    "facade": ((0.45, 0.44, 0.42), (0.78, 0.76, 0.72)),
    "decor_red": ((0.55, 0.03, 0.05), (0.90, 0.15, 0.12)),
    "decor_gold": ((0.65, 0.48, 0.10), (0.95, 0.82, 0.35)),
    "snow": ((0.80, 0.84, 0.90), (0.98, 0.98, 1.00)),
    "cactus": ((0.15, 0.32, 0.12), (0.35, 0.55, 0.25)),
    "fabric": ((0.25, 0.30, 0.55), (0.80, 0.75, 0.65)),
    "car": ((0.35, 0.10, 0.10), (0.75, 0.30, 0.25)),
    "floor": ((0.35, 0.22, 0.12), (0.70, 0.52, 0.32)),
    "tile": ((0.55, 0.55, 0.55), (0.90, 0.90, 0.88)),
    "wall": ((0.72, 0.66, 0.55), (0.93, 0.89, 0.80)),
    "ceiling": ((0.82, 0.82, 0.80), (0.96, 0.96, 0.94)),
    "rug": ((0.45, 0.10, 0.12), (0.85, 0.70, 0.45)),
    "books": ((0.25, 0.12, 0.10), (0.80, 0.65, 0.45)),
    "painting": ((0.10, 0.10, 0.10), (0.95, 0.90, 0.80)),
    "cardboard": ((0.50, 0.36, 0.20), (0.75, 0.60, 0.40)),
    "marble": ((0.75, 0.74, 0.72), (0.97, 0.96, 0.95)),
    "plant": ((0.08, 0.25, 0.08), (0.35, 0.60, 0.20)),
    "ice": ((0.55, 0.70, 0.82), (0.85, 0.93, 0.98)),
}
THEME_PALETTES: dict[str, dict[str, tuple[Rgb, Rgb]]] = {
    "snow": {
        "ground": ((0.78, 0.82, 0.88), (0.98, 0.98, 1.00)),
        "roof": ((0.82, 0.85, 0.90), (0.98, 0.98, 1.00)),
        "rock": ((0.45, 0.47, 0.52), (0.85, 0.87, 0.92)),
        "crown": ((0.40, 0.45, 0.40), (0.90, 0.92, 0.95)),
    },
    "christmas": {
        "ground": ((0.80, 0.84, 0.90), (0.98, 0.98, 1.00)),
        "roof": ((0.82, 0.86, 0.92), (0.99, 0.99, 1.00)),
        "brick": ((0.50, 0.08, 0.08), (0.80, 0.25, 0.20)),
        "conifer": ((0.02, 0.22, 0.06), (0.15, 0.45, 0.15)),
        "rock": ((0.45, 0.47, 0.52), (0.85, 0.87, 0.92)),
        "wall": ((0.55, 0.08, 0.10), (0.85, 0.30, 0.25)),
        "rug": ((0.05, 0.35, 0.12), (0.85, 0.12, 0.12)),
    },
    "autumn": {
        "ground": ((0.35, 0.25, 0.10), (0.70, 0.55, 0.25)),
        "crown": ((0.55, 0.15, 0.03), (0.95, 0.60, 0.10)),
        "conifer": ((0.10, 0.22, 0.08), (0.40, 0.40, 0.15)),
    },
    "desert": {
        "ground": ((0.70, 0.52, 0.30), (0.93, 0.80, 0.55)),
        "rock": ((0.50, 0.28, 0.15), (0.82, 0.55, 0.35)),
        "plaster": ((0.70, 0.50, 0.32), (0.90, 0.72, 0.50)),
    },
    "beach": {
        "ground": ((0.78, 0.68, 0.48), (0.97, 0.90, 0.72)),
        "crown": ((0.15, 0.40, 0.10), (0.45, 0.70, 0.20)),
        "plaster": ((0.85, 0.85, 0.85), (1.00, 1.00, 0.98)),
        "fabric": ((0.90, 0.30, 0.15), (0.98, 0.95, 0.85)),
    },
    "forest": {
        "ground": ((0.16, 0.22, 0.08), (0.42, 0.38, 0.18)),
        "crown": ((0.06, 0.24, 0.06), (0.30, 0.55, 0.15)),
    },
    "city": {
        "ground": ((0.20, 0.20, 0.21), (0.48, 0.48, 0.47)),
    },
}

OUTDOOR_WORDS = (
    "outdoor",
    "outdoors",
    "outside",
    "street",
    "landscape",
    "garden",
    "park",
    "village",
    "field",
    "mountain",
    "mountains",
)
INDOOR_WORDS = (
    "room",
    "kitchen",
    "bedroom",
    "livingroom",
    "office",
    "interior",
    "indoor",
    "indoors",
    "inside",
    "hall",
    "hallway",
    "library",
    "museum",
    "gallery",
    "classroom",
    "bathroom",
    "corridor",
    "apartment",
    "lobby",
    "studio",
    "attic",
    "basement",
)
ROOM_TYPES: dict[str, tuple[str, ...]] = {
    "kitchen": ("kitchen", "dining"),
    "bedroom": ("bedroom", "bed", "dorm"),
    "library": ("library", "books", "bookstore", "study"),
    "museum": ("museum", "gallery", "exhibition", "statue", "statues"),
    "office": ("office", "classroom", "desk", "workspace"),
    "living_room": ("living", "lounge", "sofa", "apartment"),
}
THEME_WORDS: dict[str, tuple[str, ...]] = {
    "christmas": ("christmas", "xmas", "santa", "festive"),
    "snow": ("snow", "snowy", "winter", "frozen", "icy", "ice", "wintry", "arctic"),
    "autumn": ("autumn", "fall", "autumnal", "maple", "harvest"),
    "desert": ("desert", "dune", "dunes", "sand", "sahara", "cactus", "canyon", "arid"),
    "beach": ("beach", "ocean", "sea", "coast", "shore", "island", "seaside", "tropical", "lake"),
    "city": ("city", "urban", "downtown", "skyscraper", "skyscrapers", "buildings", "metropolis", "street"),
    "forest": ("forest", "woods", "woodland", "jungle", "pine", "pines", "grove"),
}
NIGHT_WORDS = ("night", "midnight", "dark", "moonlit", "moonlight", "evening", "nighttime", "starry")


@dataclass(frozen=True)
class Sky:
    """Sky appearance. Colours are RGB in [0,1]; sun_dir is the world unit vector towards the light."""

    zenith: np.ndarray
    horizon: np.ndarray
    cloud: np.ndarray
    cloud_cover: float
    sun_dir: np.ndarray
    sun_color: np.ndarray
    ambient: float
    sun_strength: float


@dataclass(frozen=True)
class WorldObject:
    """One movable object: its kind, pivot (x, y, ground z) and footprint radius in metres."""

    id: int
    kind: str
    pivot: tuple[float, float, float]
    radius_m: float


@dataclass
class World:
    """A procedural scene: a triangle soup with one material and one object id per triangle.

    vertices (V,3) float32 world metres; triangles (F,3) int32; tri_material (F,) int32 indexes
    `MATERIALS`; tri_object (F,) int32 (0 = static ground/room shell, k >= 1 = `objects[k-1]`),
    vert_object (V,) int32 likewise (objects never share vertices); tri_part (F,) int32 numbers the
    primitives (a book, a rock) so their colours can vary. colors_a/colors_b (M,3) float32 are the
    palette of this world; texture_offset shifts the solid texture so worlds with equal materials differ.
    Geometry is always in native metres; scene_scale only changes the units the world is presented in
    (`start_pose`, and through the video backend its paths, poses and depth). terrain (outdoor worlds: the
    ground's height function) and params (the layout's sizes) let content be placed later (video/content.py).
    """

    kind: Literal["outdoor", "indoor"]
    theme: str
    layout: str
    night: bool
    vertices: np.ndarray
    triangles: np.ndarray
    tri_material: np.ndarray
    tri_object: np.ndarray
    vert_object: np.ndarray
    tri_part: np.ndarray
    objects: list[WorldObject]
    colors_a: np.ndarray
    colors_b: np.ndarray
    sky: Sky
    texture_offset: np.ndarray
    start: np.ndarray
    scene_scale: float = 1.0
    terrain: Terrain | None = field(default=None, repr=False, compare=False)
    params: WorldParams = field(default_factory=WorldParams, repr=False, compare=False)
    _scene: Any = field(default=None, repr=False, compare=False)
    cache: dict[Any, Any] = field(default_factory=dict, repr=False, compare=False)

    def start_pose(self) -> np.ndarray:
        """W2C (4,4) float64 pose where the first video starts, in scene units (native metres times
        `scene_scale`: the frame the video backend consumes and reports in)."""
        pose = self.start.copy()
        pose[:3, 3] *= self.scene_scale
        return pose

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """The Open3D ray-casting scene of this world's mesh (built on first use, not pickled)."""
        if self._scene is None:
            self._scene = make_scene(self.vertices, self.triangles)
        return self._scene

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_scene"] = None
        state["cache"] = {}  # derived data (shadow maps); rebuilt on use
        return state


def make_scene(vertices: np.ndarray, triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """An Open3D RaycastingScene holding one triangle mesh (geometry id 0)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
    )
    return scene


# ---------------------------------------------------------------- prompt analysis


def prompt_words(prompt: str) -> set[str]:
    """Lower-case word tokens of a prompt ("living room" also yields "livingroom")."""
    words = re.findall(r"[a-z]+", prompt.lower())
    return set(words) | {a + b for a, b in itertools.pairwise(words)}


def prompt_seed(prompt: str, seed: int) -> np.random.SeedSequence:
    """Seed sequence from a stable sha256 of the normalised prompt and the seed (never Python's hash())."""
    norm = " ".join(prompt.lower().split())
    digest = hashlib.sha256(norm.encode("utf-8")).digest()
    return np.random.SeedSequence([int.from_bytes(digest[i : i + 4], "little") for i in range(0, 16, 4)] + [seed])


def classify_prompt(prompt: str, world: Literal["auto", "outdoor", "indoor"] = "auto") -> tuple[str, str, str, bool]:
    """(kind, theme, layout, night) that the prompt's words suggest.

    kind: "outdoor" | "indoor"; theme: the palette ("christmas", "snow", "autumn", "desert", "beach",
    "city", "forest", "meadow", or for rooms the room type); layout: what gets placed (outdoor landscape
    or room type).
    """
    words = prompt_words(prompt)
    kind = world
    if kind == "auto":
        indoor = len(words & set(INDOOR_WORDS))
        outdoor = len(words & set(OUTDOOR_WORDS))
        kind = "indoor" if indoor > outdoor else "outdoor"
    palette = next((t for t, ws in THEME_WORDS.items() if words & set(ws)), None)
    night = bool(words & set(NIGHT_WORDS))
    if kind == "indoor":
        room = next((r for r, ws in ROOM_TYPES.items() if words & set(ws)), "room")
        return kind, ("christmas" if palette == "christmas" else room), room, night
    landscapes = ("desert", "beach", "city", "forest")
    layout = next((t for t in landscapes if words & set(THEME_WORDS[t])), "meadow")
    return kind, palette or layout, layout, night


# ---------------------------------------------------------------- mesh primitives

Mesh = tuple[np.ndarray, np.ndarray]

_BOX_V = (
    np.array(
        [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]],
        dtype=np.float64,
    )
    * 0.5
)
_BOX_F = np.array(
    [
        [0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
        [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
    ]
)  # fmt: skip


def box(size: np.ndarray | tuple[float, float, float]) -> Mesh:
    """Axis-aligned box centred at the origin with edge lengths `size`; outward winding."""
    return _BOX_V * np.asarray(size, dtype=np.float64), _BOX_F


def frustum(r_bottom: float, r_top: float, height: float, segments: int, caps: bool = True) -> Mesh:
    """Cylinder, cone (r_top = 0) or truncated cone standing on z = 0 around the z axis."""
    a = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)
    bottom = np.column_stack([ring * r_bottom, np.zeros(segments)])
    i = np.arange(segments)
    j = (i + 1) % segments
    if r_top <= 0:
        verts = np.vstack([bottom, [[0.0, 0.0, height]]])
        faces = [np.column_stack([i, j, np.full(segments, segments)])]
    else:
        top = np.column_stack([ring * r_top, np.full(segments, height)])
        verts = np.vstack([bottom, top])
        faces = [np.column_stack([i, j, j + segments]), np.column_stack([i, j + segments, i + segments])]
        if caps:
            verts = np.vstack([verts, [[0.0, 0.0, height]]])
            faces.append(np.column_stack([i + segments, j + segments, np.full(segments, len(verts) - 1)]))
    if caps:
        verts = np.vstack([verts, [[0.0, 0.0, 0.0]]])
        faces.append(np.column_stack([j, i, np.full(segments, len(verts) - 1)]))
    return verts, np.vstack(faces)


@cache
def _icosphere() -> Mesh:
    """Unit icosphere, one subdivision (42 vertices, 80 faces)."""
    t = (1 + 5**0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]  # fmt: skip
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
         [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]  # fmt: skip
    verts = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in v]
    mid: dict[tuple[int, int], int] = {}

    def midpoint(a: int, b: int) -> int:
        key = (min(a, b), max(a, b))
        if key not in mid:
            m = verts[a] + verts[b]
            verts.append(m / np.linalg.norm(m))
            mid[key] = len(verts) - 1
        return mid[key]

    faces = []
    for a, b, c in f:
        ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
        faces += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
    return np.array(verts), np.array(faces)


def blob(radius: float, rng: np.random.Generator, jitter: float, squash: float = 1.0) -> Mesh:
    """Lumpy sphere (rock, bush, crown) of mean `radius`, z scaled by `squash`, centred at the origin."""
    v, f = _icosphere()
    r = radius * (1.0 + jitter * rng.uniform(-1.0, 1.0, size=(len(v), 1)))
    out = v * r
    out[:, 2] *= squash
    return out, f


def gable_roof(width: float, depth: float, height: float, overhang: float) -> Mesh:
    """Pitched roof with its ridge along x, eaves on z = 0, closed underneath."""
    w, d = width / 2 + overhang, depth / 2 + overhang
    v = np.array([[-w, -d, 0], [w, -d, 0], [w, d, 0], [-w, d, 0], [-w, 0, height], [w, 0, height]], dtype=float)
    f = np.array([[0, 1, 5], [0, 5, 4], [2, 3, 4], [2, 4, 5], [1, 2, 5], [3, 0, 4], [0, 2, 1], [0, 3, 2]])
    return v, f


def heightfield(xs: np.ndarray, ys: np.ndarray, z: np.ndarray) -> Mesh:
    """Grid mesh over xs (nx,) by ys (ny,) with heights z (ny, nx)."""
    gx, gy = np.meshgrid(xs, ys)
    v = np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])
    nx, ny = len(xs), len(ys)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    f = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return v, f


def _place(mesh: Mesh, pos: np.ndarray | tuple[float, ...], yaw: float = 0.0) -> Mesh:
    """Rotate a mesh by `yaw` (radians) about z, then translate it to `pos`."""
    v, f = mesh
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return v @ R.T + np.asarray(pos, dtype=np.float64), f


class MeshBuilder:
    """Collects parts (mesh, material, object id) into one triangle soup."""

    def __init__(self) -> None:
        self.verts: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self.mats: list[np.ndarray] = []
        self.tri_objs: list[np.ndarray] = []
        self.vert_objs: list[np.ndarray] = []
        self.parts: list[np.ndarray] = []
        self.count = 0
        self.objects: list[WorldObject] = []

    def add(self, mesh: Mesh, material: str, obj: int = 0) -> None:
        v, f = mesh
        self.verts.append(np.asarray(v, dtype=np.float64))
        self.faces.append(np.asarray(f, dtype=np.int64) + self.count)
        self.mats.append(np.full(len(f), MATERIAL_IDS[material], dtype=np.int32))
        self.tri_objs.append(np.full(len(f), obj, dtype=np.int32))
        self.vert_objs.append(np.full(len(v), obj, dtype=np.int32))
        self.parts.append(np.full(len(f), len(self.parts), dtype=np.int32))
        self.count += len(v)

    def new_object(self, kind: str, pivot: tuple[float, float, float], radius_m: float) -> int:
        oid = len(self.objects) + 1
        self.objects.append(WorldObject(oid, kind, tuple(float(x) for x in pivot), float(radius_m)))
        return oid

    def arrays(self) -> tuple[np.ndarray, ...]:
        return (
            np.vstack(self.verts).astype(np.float32),
            np.vstack(self.faces).astype(np.int32),
            np.concatenate(self.mats),
            np.concatenate(self.tri_objs),
            np.concatenate(self.vert_objs),
            np.concatenate(self.parts),
        )


# ---------------------------------------------------------------- outdoor worlds


class Terrain:
    """Height function of the outdoor ground: gentle hills, a skyline rim and (beach) a sea shore."""

    def __init__(self, rng: np.random.Generator, p: WorldParams, layout: str) -> None:
        self.p = p
        n = 5
        ang = rng.uniform(0, 2 * np.pi, n)
        wl = rng.uniform(*p.hill_wavelength_m, n)
        self.k = np.stack([np.cos(ang), np.sin(ang)], axis=1) * (2 * np.pi / wl)[:, None]
        self.phase = rng.uniform(0, 2 * np.pi, n)
        scale = {"city": 0.15, "desert": 1.8, "beach": 0.5}.get(layout, 1.0)
        self.amp = p.hill_height_m * scale * rng.uniform(0.5, 1.0, n) / np.sqrt(n)
        self.rim_phase = rng.uniform(0, 2 * np.pi, 4)
        self.sea_dir = None
        if layout == "beach":
            a = rng.uniform(0, 2 * np.pi)
            self.sea_dir = np.array([np.cos(a), np.sin(a)])

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        p = self.p
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        r = np.hypot(x, y)
        h = sum(a * np.sin(k[0] * x + k[1] * y + ph) for a, k, ph in zip(self.amp, self.k, self.phase, strict=True))
        h = h * _smoothstep(p.clear_radius_m, p.flat_radius_m + p.clear_radius_m, r)
        theta = np.arctan2(y, x)
        skyline = 0.65 + 0.35 * sum(np.cos((i + 2) * theta + ph) for i, ph in enumerate(self.rim_phase)) / 4
        h = h + p.rim_height_m * skyline * _smoothstep(p.rim_start_m, p.terrain_radius_m, r)
        if self.sea_dir is not None:
            along = x * self.sea_dir[0] + y * self.sea_dir[1]
            shore = _smoothstep(p.shore_distance_m, p.shore_distance_m + 10.0, along)
            h = h * (1 - shore) - p.shore_drop_m * shore + 0.4
        return h

    def is_dry(self, x: float, y: float) -> bool:
        return self.sea_dir is None or float(self.height(x, y)) > 0.3


def _smoothstep(a: float, b: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((np.asarray(x) - a) / (b - a), 0.0, 1.0)
    return t * t * (3 - 2 * t)


# object kind -> share of WorldParams.outdoor_objects, per layout
OUTDOOR_LAYOUTS: dict[str, dict[str, float]] = {
    "meadow": {
        "house": 0.12,
        "tree": 0.3,
        "conifer": 0.1,
        "rock": 0.15,
        "fence": 0.1,
        "lamp": 0.08,
        "bush": 0.15,
    },
    "forest": {"tree": 0.45, "conifer": 0.55, "rock": 0.2, "bush": 0.25, "house": 0.02},
    "city": {"building": 0.35, "lamp": 0.15, "car": 0.15, "tree": 0.1, "bench": 0.08},
    "desert": {"cactus": 0.35, "rock": 0.35, "house": 0.06, "fence": 0.05},
    "beach": {"palm": 0.25, "rock": 0.2, "umbrella": 0.12, "house": 0.05, "bush": 0.1},
}
# Larger objects are placed first so the small ones fill the gaps.
PLACEMENT_ORDER = (
    "building", "house", "tree", "conifer", "palm", "fence", "car", "rock", "cactus", "umbrella", "bench",
    "lamp", "bush", "snowman",
)  # fmt: skip


class _Ctx:
    """What object builders need: the mesh builder, random numbers, terrain, theme."""

    def __init__(self, b: MeshBuilder, rng: np.random.Generator, p: WorldParams, theme: str, night: bool) -> None:
        self.b, self.rng, self.p, self.theme, self.night = b, rng, p, theme, night
        self.seg = p.cylinder_segments
        self.wintry = theme in ("snow", "christmas")


def _house(c: _Ctx, pos: np.ndarray, yaw: float, obj: int, dims: np.ndarray) -> None:
    rng, b = c.rng, c.b
    w, d, h = dims
    flat_roof = c.theme == "desert"
    wall = "plaster" if flat_roof or rng.random() < 0.4 else "brick"
    b.add(_place(box((w, d, h)), pos + [0, 0, h / 2 - 0.3], yaw), wall, obj)
    top = pos + [0, 0, h - 0.3]
    if flat_roof:
        b.add(_place(box((w + 0.2, d + 0.2, 0.25)), top + [0, 0, 0.12], yaw), "plaster", obj)
    else:
        b.add(_place(gable_roof(w, d, rng.uniform(1.2, 2.2), 0.4), top, yaw), "roof", obj)
        chim = np.array([rng.uniform(-w / 3, w / 3), d / 5, 0.0])
        b.add(_place(box((0.5, 0.5, 1.8)), top + _rot(chim, yaw) + [0, 0, 0.9], yaw), "brick", obj)
    window = "light" if c.night or c.theme == "christmas" else "glass"
    for side in (-1, 1):  # windows and a door on both long faces
        for u in (-w / 3, w / 3):
            wpos = _rot(np.array([u, side * (d / 2 + 0.03), h * 0.55]), yaw)
            b.add(_place(box((0.9, 0.08, 0.9)), pos + wpos - [0, 0, 0.3], yaw), window, obj)
        dpos = _rot(np.array([0.0, side * (d / 2 + 0.04), 0.75]), yaw)
        b.add(_place(box((0.9, 0.1, 1.9)), pos + dpos - [0, 0, 0.2], yaw), "wood", obj)
    if c.theme == "christmas":  # a string of coloured lights under the eaves
        for i, u in enumerate(np.linspace(-w / 2, w / 2, 9)):
            lpos = _rot(np.array([u, -(d / 2 + 0.1), h - 0.45]), yaw)
            b.add(_place(blob(0.09, rng, 0.0), pos + lpos), "decor_red" if i % 2 else "decor_gold", obj)


def _rot(v: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


def _building(c: _Ctx, pos: np.ndarray, yaw: float, obj: int, dims: np.ndarray) -> None:
    w, d, h = dims
    c.b.add(_place(box((w, d, h)), pos + [0, 0, h / 2 - 0.3], yaw), "facade", obj)
    c.b.add(_place(box((w + 0.4, d + 0.4, 0.4)), pos + [0, 0, h - 0.1], yaw), "roof" if c.wintry else "metal", obj)
    c.b.add(_place(box((w * 0.3, d * 0.3, 1.5)), pos + [0, 0, h + 0.6], yaw), "metal", obj)


def _tree(c: _Ctx, pos: np.ndarray, obj: int, height: float) -> None:
    rng = c.rng
    trunk_h = height * rng.uniform(0.35, 0.5)
    r = height * 0.035
    c.b.add(_place(frustum(r * 1.3, r, trunk_h + 0.4, c.seg), pos - [0, 0, 0.4]), "bark", obj)
    crown_r = height * rng.uniform(0.25, 0.35)
    if rng.random() < 0.5:
        crown = blob(crown_r, rng, 0.15, squash=1.2)
        c.b.add(_place(crown, pos + [0, 0, trunk_h + crown_r * 0.9]), "crown", obj)
    else:  # a cone crown
        cone = frustum(crown_r * 1.2, 0.0, height - trunk_h + 0.5, c.seg)
        c.b.add(_place(cone, pos + [0, 0, trunk_h - 0.5]), "crown", obj)


def _conifer(c: _Ctx, pos: np.ndarray, obj: int, height: float) -> None:
    rng = c.rng
    r = height * 0.03
    c.b.add(_place(frustum(r * 1.2, r, height * 0.3 + 0.4, c.seg), pos - [0, 0, 0.4]), "bark", obj)
    tiers = 3
    base = height * 0.22
    for i in range(tiers):
        cr = height * 0.28 * (1 - 0.22 * i)
        z0 = base + i * height * 0.2
        tier_h = height - z0 if i == tiers - 1 else height * 0.4
        c.b.add(_place(frustum(cr, 0.0, tier_h, c.seg), pos + [0, 0, z0], rng.uniform(0, np.pi)), "conifer", obj)
        if c.wintry:  # snow caps
            cap = frustum(cr * 0.35, 0.0, tier_h * 0.35, c.seg)
            c.b.add(_place(cap, pos + [0, 0, z0 + tier_h * 0.66]), "snow", obj)
    if c.theme == "christmas":  # baubles around the tiers
        for i in range(14):
            t = rng.uniform(0.05, 0.75)
            zz = base + t * (height - base)
            rr = height * 0.28 * (1 - t) * 0.95 + 0.05
            a = rng.uniform(0, 2 * np.pi)
            mat = "decor_red" if i % 2 else "decor_gold"
            c.b.add(
                _place(blob(0.12 + height * 0.01, rng, 0.0), pos + [rr * np.cos(a), rr * np.sin(a), zz]),
                mat,
                obj,
            )
        c.b.add(_place(blob(0.25, rng, 0.0), pos + [0, 0, height + 0.1]), "decor_gold", obj)


def _palm(c: _Ctx, pos: np.ndarray, obj: int, height: float) -> None:
    rng = c.rng
    lean = np.clip(rng.normal(0, 0.4, 2), -0.6, 0.6)
    segs = 5
    for i in range(segs):
        z0 = height * i / segs
        off = np.array([lean[0], lean[1], 0.0]) * (i / segs) ** 2
        piece = frustum(0.22 - 0.02 * i, 0.2 - 0.02 * i, height / segs + 0.05, c.seg)
        c.b.add(_place(piece, pos + off + [0, 0, z0 - 0.2]), "bark", obj)
    top = pos + np.array([lean[0], lean[1], height - 0.2])
    for k in range(7):  # leaves: flat squashed blobs fanned out around the top
        a = 2 * np.pi * k / 7 + rng.uniform(-0.2, 0.2)
        leaf = blob(1.0, rng, 0.1)
        v = leaf[0] * [1.6, 0.35, 0.12]
        c.b.add(_place((v, leaf[1]), top + [1.3 * np.cos(a), 1.3 * np.sin(a), -0.3], a), "crown", obj)


def _rock(c: _Ctx, pos: np.ndarray, obj: int, radius: float) -> None:
    c.b.add(_place(blob(radius, c.rng, 0.25, squash=0.6), pos, c.rng.uniform(0, np.pi)), "rock", obj)


def _bush(c: _Ctx, pos: np.ndarray, obj: int, radius: float) -> None:
    mat = "snow" if c.wintry and c.rng.random() < 0.5 else "crown"
    c.b.add(_place(blob(radius, c.rng, 0.2, squash=0.75), pos + [0, 0, radius * 0.4]), mat, obj)


def _fence(c: _Ctx, pos: np.ndarray, yaw: float, obj: int, length: float) -> None:
    n_posts = max(2, int(length / 1.6) + 1)
    for u in np.linspace(-length / 2, length / 2, n_posts):
        c.b.add(_place(box((0.14, 0.14, 1.4)), pos + _rot(np.array([u, 0.0, 0.5]), yaw), yaw), "wood", obj)
    for z in (0.5, 0.95):
        c.b.add(_place(box((length, 0.06, 0.14)), pos + [0, 0, z], yaw), "wood", obj)


def _lamp(c: _Ctx, pos: np.ndarray, obj: int, height: float) -> None:
    c.b.add(_place(frustum(0.08, 0.06, height + 0.3, c.seg), pos - [0, 0, 0.3]), "metal", obj)
    c.b.add(_place(box((0.35, 0.35, 0.45)), pos + [0, 0, height + 0.2]), "light", obj)
    c.b.add(_place(frustum(0.35, 0.0, 0.3, 4), pos + [0, 0, height + 0.42], np.pi / 4), "metal", obj)


def _car(c: _Ctx, pos: np.ndarray, yaw: float, obj: int) -> None:
    c.b.add(_place(box((4.2, 1.8, 0.8)), pos + [0, 0, 0.7], yaw), "car", obj)
    c.b.add(_place(box((2.2, 1.6, 0.6)), pos + _rot(np.array([-0.3, 0.0, 1.4]), yaw), yaw), "glass", obj)
    for u in (-1.3, 1.3):
        for s in (-0.9, 0.9):
            wpos = _rot(np.array([u, s, 0.35]), yaw)
            c.b.add(_place(box((0.7, 0.25, 0.7)), pos + wpos, yaw), "metal", obj)


def _bench(c: _Ctx, pos: np.ndarray, yaw: float, obj: int) -> None:
    c.b.add(_place(box((1.8, 0.5, 0.08)), pos + [0, 0, 0.45], yaw), "wood", obj)
    c.b.add(_place(box((1.8, 0.06, 0.45)), pos + _rot(np.array([0.0, 0.25, 0.75]), yaw), yaw), "wood", obj)
    for u in (-0.8, 0.8):
        c.b.add(_place(box((0.08, 0.45, 0.45)), pos + _rot(np.array([u, 0.0, 0.2]), yaw), yaw), "metal", obj)


def _cactus(c: _Ctx, pos: np.ndarray, obj: int, height: float) -> None:
    rng = c.rng
    c.b.add(_place(frustum(0.3, 0.25, height + 0.3, c.seg), pos - [0, 0, 0.3]), "cactus", obj)
    for side in (-1, 1):
        if rng.random() < 0.7:
            z = height * rng.uniform(0.35, 0.6)
            c.b.add(_place(box((0.9, 0.3, 0.3)), pos + _rot(np.array([side * 0.55, 0.0, z]), 0.0)), "cactus", obj)
            c.b.add(_place(frustum(0.17, 0.15, height * 0.35, c.seg), pos + [side * 0.9, 0, z]), "cactus", obj)


def _umbrella(c: _Ctx, pos: np.ndarray, obj: int) -> None:
    c.b.add(_place(frustum(0.04, 0.04, 2.6, 6), pos - [0, 0, 0.3]), "metal", obj)
    c.b.add(_place(frustum(1.4, 0.0, 0.6, c.seg), pos + [0, 0, 1.9]), "fabric", obj)


def _snowman(c: _Ctx, pos: np.ndarray, obj: int) -> None:
    for z, r in ((0.45, 0.55), (1.2, 0.4), (1.75, 0.28)):
        c.b.add(_place(blob(r, c.rng, 0.03), pos + [0, 0, z]), "snow", obj)
    c.b.add(_place(frustum(0.06, 0.0, 0.35, 6), pos + [0, -0.22, 1.75]), "decor_red", obj)
    c.b.add(_place(frustum(0.2, 0.18, 0.35, c.seg), pos + [0, 0, 1.95]), "metal", obj)


def _outdoor_object(c: _Ctx, kind: str) -> tuple[float, Any]:
    """(footprint radius, builder(pos, obj)) of one random instance of `kind`."""
    rng = c.rng
    yaw = rng.uniform(0, 2 * np.pi)
    if kind == "house":
        dims = np.array([rng.uniform(5, 8), rng.uniform(4, 6.5), rng.uniform(2.8, 4.0)])
        return float(np.hypot(dims[0], dims[1]) / 2 + 0.6), lambda p, o: _house(c, p, yaw, o, dims)
    if kind == "building":
        dims = np.array([rng.uniform(6, 12), rng.uniform(6, 12), rng.uniform(8, 26)])
        return float(np.hypot(dims[0] + 0.4, dims[1] + 0.4) / 2), lambda p, o: _building(c, p, yaw, o, dims)
    if kind in ("tree", "conifer", "palm", "lamp", "cactus"):
        h = {"tree": (5, 10), "conifer": (5, 12), "palm": (5, 9), "lamp": (3.5, 4.5), "cactus": (1.8, 4)}[kind]
        height = rng.uniform(*h)
        # footprint radius: the widest part (crown, tiers, leaves, arms) with its random jitter
        fp = {"tree": 0.45, "conifer": 0.3, "palm": 0.0, "lamp": 0.1, "cactus": 0.0}[kind] * height + 0.3
        fp = {"palm": 4.2, "cactus": 1.2}.get(kind, fp)
        fn = {"tree": _tree, "conifer": _conifer, "palm": _palm, "lamp": _lamp, "cactus": _cactus}[kind]
        return max(fp, 0.4), lambda p, o: fn(c, p, o, height)
    if kind in ("rock", "bush"):
        radius = rng.uniform(0.4, 1.8) if kind == "rock" else rng.uniform(0.5, 1.2)
        fn2 = _rock if kind == "rock" else _bush
        return radius * 1.3, lambda p, o: fn2(c, p, o, radius)
    if kind == "fence":
        length = rng.uniform(4, 10)
        return length / 2 + 0.15, lambda p, o: _fence(c, p, yaw, o, length)
    if kind == "car":
        return 2.3, lambda p, o: _car(c, p, yaw, o)
    if kind == "bench":
        return 1.0, lambda p, o: _bench(c, p, yaw, o)
    if kind == "umbrella":
        return 1.4, lambda p, o: _umbrella(c, p, o)
    if kind == "snowman":
        return 0.6, lambda p, o: _snowman(c, p, o)
    raise ValueError(f"unknown outdoor object kind {kind!r}")


def _build_outdoor(c: _Ctx, layout: str) -> Terrain:
    p, rng, b = c.p, c.rng, c.b
    terrain = Terrain(rng, p, layout)
    n = int(np.ceil(p.terrain_radius_m / p.terrain_cell_m))
    xs = np.linspace(-p.terrain_radius_m, p.terrain_radius_m, 2 * n + 1)
    gx, gy = np.meshgrid(xs, xs)
    b.add(heightfield(xs, xs, terrain.height(gx, gy)), "ground")
    if layout == "beach":
        r = p.terrain_radius_m
        b.add(
            (
                np.array([[-r, -r, 0.0], [r, -r, 0.0], [r, r, 0.0], [-r, r, 0.0]]),
                np.array([[0, 1, 2], [0, 2, 3]]),
            ),
            "water",
        )
    shares = dict(OUTDOOR_LAYOUTS[layout])
    if c.wintry:
        shares["conifer"] = shares.get("conifer", 0.0) + 0.15
        shares.pop("palm", None)
    if c.theme == "christmas":
        shares["snowman"] = 0.05
    placed: list[tuple[float, float, float]] = []
    r0, r1 = p.object_radius_m
    for kind in PLACEMENT_ORDER:
        count = round(shares.get(kind, 0.0) * p.outdoor_objects)
        for _ in range(count):
            fp, build = _outdoor_object(c, kind)
            for _try in range(p.placement_tries):
                a = rng.uniform(0, 2 * np.pi)
                lo = max(r0, p.clear_radius_m + fp)
                if lo >= r1:
                    break
                r = np.sqrt(rng.uniform(lo**2, r1**2))  # uniform over the annulus' area
                x, y = r * np.cos(a), r * np.sin(a)
                if not terrain.is_dry(x, y):
                    continue
                if all(np.hypot(x - qx, y - qy) >= fp + qr + p.object_gap_m for qx, qy, qr in placed):
                    z = float(terrain.height(x, y))
                    placed.append((x, y, fp))
                    build(np.array([x, y, z]), b.new_object(kind, (x, y, z), fp))
                    break
    return terrain


# ---------------------------------------------------------------- indoor worlds

INDOOR_LAYOUTS: dict[str, dict[str, float]] = {
    "room": {
        "table": 0.15,
        "shelf": 0.15,
        "sofa": 0.1,
        "box": 0.2,
        "lamp": 0.1,
        "painting": 0.2,
        "plant": 0.1,
    },
    "kitchen": {"counter": 0.3, "table": 0.15, "shelf": 0.1, "box": 0.1, "plant": 0.1, "painting": 0.15},
    "bedroom": {
        "bed": 0.08,
        "wardrobe": 0.1,
        "table": 0.1,
        "shelf": 0.1,
        "lamp": 0.12,
        "painting": 0.2,
        "box": 0.1,
    },
    "library": {"shelf": 0.6, "table": 0.12, "lamp": 0.1, "painting": 0.1},
    "museum": {"pedestal": 0.35, "painting": 0.45, "plant": 0.05},
    "office": {"table": 0.3, "shelf": 0.2, "box": 0.2, "lamp": 0.1, "painting": 0.1, "plant": 0.1},
    "living_room": {
        "sofa": 0.15,
        "table": 0.12,
        "shelf": 0.15,
        "lamp": 0.12,
        "painting": 0.2,
        "plant": 0.1,
        "box": 0.05,
    },
}
WALL_ITEMS = ("painting",)
AGAINST_WALL = ("shelf", "counter", "wardrobe", "bed", "sofa")


def _indoor_item(c: _Ctx, kind: str) -> tuple[tuple[float, float], Any]:
    """((width along the wall, depth), builder(pos, yaw, obj)) for one furniture item; +y local = its back."""
    rng, b, seg = c.rng, c.b, c.seg
    if kind == "table":
        w, d, h = rng.uniform(1.0, 2.0), rng.uniform(0.7, 1.1), rng.uniform(0.72, 0.78)

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            b.add(_place(box((w, d, 0.05)), p + [0, 0, h], yaw), "wood", o)
            for sx in (-1, 1):
                for sy in (-1, 1):
                    leg = _rot(np.array([sx * (w / 2 - 0.06), sy * (d / 2 - 0.06), h / 2]), yaw)
                    b.add(_place(box((0.06, 0.06, h)), p + leg, yaw), "wood", o)
            for _ in range(rng.integers(1, 4)):  # things on the table
                q = _rot(np.array([rng.uniform(-w / 3, w / 3), rng.uniform(-d / 4, d / 4), 0.0]), yaw)
                s = rng.uniform(0.15, 0.35, 3)
                b.add(
                    _place(box(s), p + q + [0, 0, h + s[2] / 2 + 0.025], rng.uniform(0, np.pi)),
                    str(rng.choice(["books", "cardboard", "metal"])),
                    o,
                )

        return (w, d), build
    if kind in ("shelf", "wardrobe"):
        w, d, h = rng.uniform(1.0, 2.0), rng.uniform(0.35, 0.6), rng.uniform(1.8, 2.4)

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            if kind == "wardrobe":
                b.add(_place(box((w, d, h)), p + [0, 0, h / 2], yaw), "wood", o)
                return
            b.add(_place(box((w, 0.04, h)), p + _rot(np.array([0, d / 2 - 0.02, h / 2]), yaw), yaw), "wood", o)
            for sx in (-1, 1):
                b.add(_place(box((0.04, d, h)), p + _rot(np.array([sx * w / 2, 0, h / 2]), yaw), yaw), "wood", o)
            levels = np.linspace(0.05, h - 0.05, 5)
            for z in levels:
                b.add(_place(box((w, d, 0.03)), p + [0, 0, z], yaw), "wood", o)
            for z0, z1 in itertools.pairwise(levels):  # books of random widths and heights
                u = -w / 2 + 0.04
                while True:
                    bw = rng.uniform(0.03, 0.08)
                    if u + bw > w / 2 - 0.04:
                        break
                    bh = (z1 - z0) * rng.uniform(0.55, 0.9)
                    q = _rot(np.array([u + bw / 2, 0.02, z0 + 0.015 + bh / 2]), yaw)
                    b.add(_place(box((bw, d * 0.8, bh)), p + q, yaw), "books", o)
                    u += bw + rng.uniform(0.0, 0.04)

        return (w, d), build
    if kind == "counter":
        w, d = rng.uniform(1.6, 3.0), 0.65

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            b.add(_place(box((w, d, 0.88)), p + [0, 0, 0.44], yaw), "wood", o)
            b.add(_place(box((w + 0.04, d + 0.04, 0.04)), p + [0, 0, 0.9], yaw), "marble", o)
            up = _rot(np.array([0.0, d / 2 - 0.18, 1.9]), yaw)
            b.add(_place(box((w, 0.35, 0.7)), p + up, yaw), "wood", o)

        return (w, d), build
    if kind in ("sofa", "bed"):
        w, d = (rng.uniform(1.8, 2.4), 0.9) if kind == "sofa" else (rng.uniform(1.4, 1.8), 2.1)

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            base = 0.45 if kind == "sofa" else 0.5
            b.add(
                _place(box((w, d, base)), p + [0, 0, base / 2], yaw),
                "fabric" if kind == "sofa" else "wood",
                o,
            )
            back = _rot(np.array([0.0, d / 2 - 0.1, base + 0.3]), yaw)
            b.add(_place(box((w, 0.2, 0.6 if kind == "sofa" else 0.9)), p + back, yaw), "fabric", o)
            if kind == "bed":
                b.add(
                    _place(box((w - 0.1, d - 0.3, 0.2)), p + _rot(np.array([0, -0.1, base + 0.1]), yaw), yaw),
                    "rug",
                    o,
                )
                pil = _rot(np.array([0.0, d / 2 - 0.4, base + 0.25]), yaw)
                b.add(_place(box((w * 0.7, 0.35, 0.15)), p + pil, yaw), "fabric", o)
            else:
                for sx in (-1, 1):
                    arm = _rot(np.array([sx * (w / 2 - 0.1), 0.0, base + 0.15]), yaw)
                    b.add(_place(box((0.2, d, 0.3)), p + arm, yaw), "fabric", o)

        return (w, d), build
    if kind == "box":
        s = rng.uniform(0.3, 0.7, 3)

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            b.add(_place(box(s), p + [0, 0, s[2] / 2], yaw), "cardboard", o)
            if rng.random() < 0.5:
                s2 = s * rng.uniform(0.5, 0.9, 3)
                b.add(_place(box(s2), p + [0, 0, s[2] + s2[2] / 2], yaw + 0.3), "cardboard", o)

        return (float(s[0]), float(s[1])), build
    if kind == "lamp":

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            b.add(_place(frustum(0.2, 0.2, 0.04, seg), p), "metal", o)
            b.add(_place(frustum(0.025, 0.025, 1.5, 6), p), "metal", o)
            b.add(_place(frustum(0.28, 0.16, 0.35, seg, caps=False), p + [0, 0, 1.35]), "light", o)

        return (0.5, 0.5), build
    if kind == "plant":
        h = rng.uniform(0.6, 1.4)

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            b.add(_place(frustum(0.18, 0.24, 0.4, seg), p), "cardboard", o)
            b.add(_place(blob(h * 0.35, rng, 0.25, squash=1.3), p + [0, 0, 0.4 + h * 0.35]), "plant", o)

        return (0.6, 0.6), build
    if kind == "pedestal":

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            b.add(_place(box((0.6, 0.6, 1.0)), p + [0, 0, 0.5], yaw), "marble", o)
            b.add(_place(blob(0.3, rng, 0.3, squash=1.5), p + [0, 0, 1.4], yaw), "rock", o)

        return (0.8, 0.8), build
    if kind == "painting":
        w, h = rng.uniform(0.6, 1.6), rng.uniform(0.5, 1.1)

        def build(p: np.ndarray, yaw: float, o: int) -> None:
            b.add(_place(box((w + 0.1, 0.04, h + 0.1)), p + [0, 0, 1.6], yaw), "wood", o)
            front = _rot(np.array([0.0, -0.025, 1.6]), yaw)
            b.add(_place(box((w, 0.02, h)), p + front, yaw), "painting", o)

        return (w + 0.1, 0.04), build
    raise ValueError(f"unknown indoor object kind {kind!r}")


def _build_indoor(c: _Ctx, layout: str) -> None:
    p, rng, b = c.p, c.rng, c.b
    sx, sy, sz = p.room_size_m
    t = p.wall_thickness_m
    floor_mat = "tile" if layout in ("kitchen", "museum") else "floor"
    b.add(_place(box((sx + 2 * t, sy + 2 * t, t)), (0, 0, -t / 2)), floor_mat)
    b.add(_place(box((sx + 2 * t, sy + 2 * t, t)), (0, 0, sz + t / 2)), "ceiling")
    b.add(_place(box((t, sy, sz)), (-(sx + t) / 2, 0, sz / 2)), "wall")
    b.add(_place(box((t, sy, sz)), ((sx + t) / 2, 0, sz / 2)), "wall")
    b.add(_place(box((sx, t, sz)), (0, -(sy + t) / 2, sz / 2)), "wall")
    b.add(_place(box((sx, t, sz)), (0, (sy + t) / 2, sz / 2)), "wall")
    for x in np.linspace(-sx / 2 + 1.5, sx / 2 - 1.5, 3):  # ceiling lights
        for y in (-sy / 4, sy / 4):
            b.add(_place(box((0.6, 0.6, 0.05)), (x, y, sz - 0.03)), "light")
    b.add(_place(box((1.0, 0.06, 2.1)), (rng.uniform(-sx / 3, sx / 3), -sy / 2 + 0.03, 1.05)), "wood")  # a door
    if layout != "museum":
        b.add(
            _place(box((rng.uniform(2.0, 3.5), rng.uniform(1.6, 2.5), 0.02)), (0, 0, 0.01), rng.uniform(0, np.pi)),
            "rug",
        )
    # walls as (centre of the wall's inner face, yaw that turns local +y towards the wall, length)
    walls = [
        (np.array([0.0, sy / 2, 0.0]), 0.0, sx),
        (np.array([0.0, -sy / 2, 0.0]), np.pi, sx),
        (np.array([sx / 2, 0.0, 0.0]), -np.pi / 2, sy),
        (np.array([-sx / 2, 0.0, 0.0]), np.pi / 2, sy),
    ]
    shares = dict(INDOOR_LAYOUTS[layout])
    if c.theme == "christmas":
        shares["xmas_tree"] = 0.05
    occupied: list[tuple[np.ndarray, np.ndarray]] = []  # axis-aligned footprints (min xy, max xy)
    wall_used: list[tuple[int, float, float]] = []
    for kind, share in shares.items():
        for _ in range(max(1, round(share * p.indoor_objects))):
            if kind == "xmas_tree":
                _place_xmas_tree(c, occupied)
                continue
            (w, d), build = _indoor_item(c, kind)
            for _try in range(p.placement_tries):
                if kind in WALL_ITEMS or kind in AGAINST_WALL or rng.random() < 0.5:
                    wi = int(rng.integers(4))
                    centre, yaw, length = walls[wi]
                    if w >= length - 0.4:
                        continue
                    u = rng.uniform(-length / 2 + w / 2 + 0.2, length / 2 - w / 2 - 0.2)
                    pos = centre + _rot(np.array([u, -d / 2 - 0.01, 0.0]), yaw)
                    if kind in WALL_ITEMS:  # hangs on the wall: only other wall items must not overlap
                        if any(j == wi and abs(u - v) < (w + lw) / 2 + 0.2 for j, v, lw in wall_used):
                            continue
                        wall_used.append((wi, u, w))
                        build(pos, yaw, b.new_object(kind, tuple(pos), max(w, d) / 2))
                        break
                else:
                    yaw = rng.choice([0.0, np.pi / 2, np.pi, -np.pi / 2]) + rng.uniform(-0.2, 0.2)
                    lim = np.array([sx / 2, sy / 2]) - max(w, d) / 2 - 0.3
                    pos = np.array([rng.uniform(-lim[0], lim[0]), rng.uniform(-lim[1], lim[1]), 0.0])
                    if np.hypot(pos[0], pos[1]) < p.indoor_clear_radius_m + max(w, d) / 2:
                        continue
                cy, sy_ = abs(np.cos(yaw)), abs(np.sin(yaw))
                half_ext = np.array([cy * w + sy_ * d, sy_ * w + cy * d]) / 2 + 0.05
                lo, hi = pos[:2] - half_ext, pos[:2] + half_ext
                if any(np.all(lo < qhi) and np.all(qlo < hi) for qlo, qhi in occupied):
                    continue
                occupied.append((lo, hi))
                build(pos, yaw, b.new_object(kind, tuple(pos), max(w, d) / 2))
                break


def _place_xmas_tree(c: _Ctx, occupied: list[tuple[np.ndarray, np.ndarray]]) -> None:
    sx, sy, _ = c.p.room_size_m
    for _try in range(c.p.placement_tries):
        pos = np.array([c.rng.uniform(-sx / 2 + 1, sx / 2 - 1), c.rng.uniform(-sy / 2 + 1, sy / 2 - 1), 0.0])
        lo, hi = pos[:2] - 0.8, pos[:2] + 0.8
        if np.hypot(*pos[:2]) < c.p.indoor_clear_radius_m + 0.8:
            continue
        if any(np.all(lo < qhi) and np.all(qlo < hi) for qlo, qhi in occupied):
            continue
        occupied.append((lo, hi))
        _conifer(c, pos, c.b.new_object("xmas_tree", tuple(pos), 0.8), 2.4)
        return


# ---------------------------------------------------------------- sky, palette, assembly


def _sky(rng: np.random.Generator, p: WorldParams, kind: str, theme: str, night: bool) -> Sky:
    if kind == "indoor":
        el, az = np.radians(p.indoor_light_elevation_deg), rng.uniform(0, 2 * np.pi)
    else:
        el = np.radians(rng.uniform(*p.sun_elevation_deg))
        az = np.radians(rng.uniform(*p.sun_azimuth_deg))
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    if night:
        return Sky(
            zenith=np.array([0.02, 0.03, 0.10]),
            horizon=np.array([0.10, 0.12, 0.25]),
            cloud=np.array([0.2, 0.22, 0.3]),
            cloud_cover=float(rng.uniform(0.2, 0.45)),
            sun_dir=sun,
            sun_color=np.array([0.55, 0.6, 0.8]),
            ambient=0.35,
            sun_strength=0.45,
        )
    horizon = {"desert": [0.85, 0.80, 0.70], "snow": [0.85, 0.88, 0.92], "christmas": [0.82, 0.86, 0.92]}
    return Sky(
        zenith=np.array([0.22, 0.42, 0.80]),
        horizon=np.array(horizon.get(theme, [0.70, 0.80, 0.92])),
        cloud=np.array([0.97, 0.97, 0.98]),
        cloud_cover=float(rng.uniform(0.25, 0.5)),
        sun_dir=sun,
        sun_color=np.array([1.0, 0.96, 0.88]),
        ambient=0.75 if kind == "indoor" else 0.45,
        sun_strength=0.4 if kind == "indoor" else 0.65,
    )


def build_world(prompt: str, seed: int, opts: Any = None) -> World:
    """The world a prompt and a seed describe; identical inputs give an identical world.

    opts: a `ProceduralOptions` (uses its `world` kind override, `layout` params and `scene_scale`) or a
    `WorldParams` or None for defaults. Returns a `World` (world frame +z up, geometry in metres).
    """
    kind_override: Literal["auto", "outdoor", "indoor"] = "auto"
    params = WorldParams()
    scene_scale = 1.0
    if isinstance(opts, WorldParams):
        params = opts
    elif opts is not None:
        kind_override = opts.world
        params = opts.layout
        scene_scale = float(opts.scene_scale)
    kind, theme, layout, night = classify_prompt(prompt, kind_override)
    rng = np.random.default_rng(prompt_seed(prompt, seed))
    builder = MeshBuilder()
    ctx = _Ctx(builder, rng, params, theme, night)
    terrain = None
    if kind == "outdoor":
        terrain = _build_outdoor(ctx, layout)
        ground_z = float(terrain.height(0.0, 0.0))
        eye = np.array([0.0, 0.0, ground_z + params.camera_height_m])
        pitch = np.radians(params.camera_pitch_deg)
    else:
        _build_indoor(ctx, layout)
        eye = np.array([0.0, 0.0, params.indoor_camera_height_m])
        pitch = np.radians(params.indoor_camera_pitch_deg)
    start = look_at(eye, eye + np.array([0.0, np.cos(pitch), -np.sin(pitch)]))
    verts, tris, mats, tri_obj, vert_obj, parts = builder.arrays()
    palette = dict(BASE_PALETTE) | THEME_PALETTES.get(theme, {})
    colors = np.array([palette[name] for name in MATERIALS], dtype=np.float32)
    return World(
        kind=kind,
        theme=theme,
        layout=layout,
        night=night,
        vertices=verts,
        triangles=tris,
        tri_material=mats,
        tri_object=tri_obj,
        vert_object=vert_obj,
        tri_part=parts,
        objects=builder.objects,
        colors_a=colors[:, 0],
        colors_b=colors[:, 1],
        sky=_sky(rng, params, kind, theme, night),
        texture_offset=rng.uniform(-100, 100, 3).astype(np.float32),
        start=start,
        scene_scale=scene_scale,
        terrain=terrain,
        params=params,
    )
