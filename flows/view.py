"""`wonderverse view SCENE_DIR`: the scene's splats in a real-time viewer in the browser.

The viewer is Spark (`@sparkjsdev/spark` 2.2.0, World Labs' Gaussian-splat renderer on three.js 0.187.0, WebGL2,
both MIT), whose built files ship inside this package (`flows/viewer_assets/`, with their licences; package data,
so `pip install` alone makes `view` work, no npm at run time); nothing is fetched from a CDN. The server (Python's
`http.server`, threaded) binds 127.0.0.1 on a free port unless told otherwise
and serves exactly two things: the viewer's files (a fixed list, under `/_viewer/`) and regular files inside
SCENE_DIR (`..`, absolute paths, encoded separators, hidden files and symlinks leading out are refused with
404). It runs in the CLI's child process, so Ctrl-C (the supervisor kills the child's process group) stops it.

The page opens at the first posed scene camera with that camera's intrinsics, renders with Spark set to the
conventions of our renderer (z-depth sorting, 0.3 px² dilation without opacity compensation, 3σ cut-off,
alpha below 1/255 skipped, the learned background colour behind the splats), and offers every training
camera (◀ ▶, keys [ and ]), the fly-through path of the outputs (▶ fly-through, key p; `flythrough_path` over
the training cameras) and orbiting with the mouse around the point the camera looks at. `#camera=K` in the
URL opens at training camera K.

Conventions. The three.js scene is the world frame of the scene's files: the outputs' gravity-aligned +Z-up
frame (the `sfm/` poses mapped by the `outputs` attrs' `frame.world_from_sfm`; the `sfm/` frame itself for a
scene whose splats.ply the splats step wrote), with +Z as the orbit's up. `splats.ply` is loaded as it is,
`splats.spz` (stored +Y up, `web.Y_UP_FROM_WORLD`) is turned back by that rotation's transpose. Our poses are
world-to-camera with OpenCV axes (x right, y down, z forward); three.js cameras are placed by their
camera-to-world matrix with OpenGL axes (x right, y up, z backward), so each camera's matrixWorld is
C2W_opencv · diag(1, -1, -1, 1).
The projection matrix is built from K (pixel centres at +0.5, so NDC -1 is the image's left edge):
[[2fx/W, 0, 1 - 2cx/W, 0], [0, 2fy/H, 2cy/H - 1, 0], [0, 0, -(f+n)/(f-n), -2fn/(f-n)], [0, 0, -1, 0]], and the
canvas keeps the training images' aspect ratio.

`view` also writes `SCENE_DIR/viewer.html`: the same page with three.js, Spark and the scene's cameras
inlined (about 5 MB), loading the splat file beside it; it works from any web server that serves the scene
folder (or from `view` itself). Opened from disk (file://), Chromium refuses to read the file beside it: the
page then asks for the splat file to be dropped onto it.
"""

from __future__ import annotations

import contextlib
import errno
import html
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any
from urllib.parse import unquote, urlsplit

import typer

from wonderverse.errors import WonderError

if TYPE_CHECKING:  # numpy and http.server load when the command runs: `wonderverse --help` stays fast
    from http.server import ThreadingHTTPServer

    import numpy as np

# The viewer's built files, copied from npm (three 0.187.0: build/three.core.js, build/three.module.js,
# examples/jsm/...; @sparkjsdev/spark 2.2.0: dist/spark.module.min.js, gzipped: 2.7 MB as it is) with their
# LICENSE files
VIEWER_ASSETS = Path(__file__).resolve().parent / "viewer_assets"
VIEWER_HTML = "viewer.html"
SPLAT_FILES = ("splats.spz", "splats.ply")  # the viewer loads the first one present (SPZ: a tenth of the bytes)
# URL path under /_viewer/ -> the built file in VIEWER_ASSETS (the only files of the viewer served)
VIEWER_FILES = {
    "three.core.js": "three.core.js",
    "three.module.js": "three.module.js",
    "addons/postprocessing/Pass.js": "addons/postprocessing/Pass.js",
    "addons/controls/OrbitControls.js": "addons/controls/OrbitControls.js",
    "spark.module.js": "spark.module.js.gz",
}
IMPORTS = {  # bare module specifiers of the page -> VIEWER_FILES key
    "three": "three.module.js",
    "three/addons/postprocessing/Pass.js": "addons/postprocessing/Pass.js",
    "three/addons/controls/OrbitControls.js": "addons/controls/OrbitControls.js",
    "@sparkjsdev/spark": "spark.module.js",
}
CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8",
    ".json": "application/json",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".mp4": "video/mp4",
    ".glb": "model/gltf-binary",
}


@dataclass(frozen=True)
class SceneView:
    """What the page needs: the splat file (a name in the scene folder) and the rotation from the world into
    its axes, the training cameras (W2C (N,4,4), OpenCV axes, world frame) with K (3,3) for width×height
    images, the fly-through path (W2C (M,4,4)) and its frame rate, the background colour (RGB in [0,1]), the
    distance the first camera looks to (world units: the orbit centre) and the scene's size."""

    splat_file: str
    file_from_world: np.ndarray
    w2c: np.ndarray
    K: np.ndarray
    width: int
    height: int
    flythrough: np.ndarray
    fps: float
    background: tuple[float, float, float]
    look_distance: float
    scene_size: float


def viewer_files() -> dict[str, bytes]:
    """The viewer's files by URL path, their contents (a `.gz` one decompressed); WonderError when the package was
    installed without them (package data left out: a broken install, not something npm should repair)."""
    import gzip

    paths = {name: VIEWER_ASSETS / rel for name, rel in VIEWER_FILES.items()}
    missing = [str(p) for p in paths.values() if not p.is_file()]
    if missing:
        raise WonderError(
            f"the splat viewer is not installed ({missing[0]} is missing): this wonderverse package was installed "
            "without its package data; reinstall it with `pip install -e .` (or `pip install .`)"
        )
    return {name: gzip.decompress(p.read_bytes()) if p.suffix == ".gz" else p.read_bytes() for name, p in paths.items()}


def _c2w_gl(w2c: np.ndarray) -> list[float]:
    """three.js's camera matrixWorld (column-major, 16 floats) of a W2C pose with OpenCV axes."""
    import numpy as np

    from wonderverse.camera import invert_se3

    return (invert_se3(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])).T.reshape(-1).tolist()


def scene_view(scene_dir: Path, splat_path: Path | None = None) -> SceneView:
    """Read what the viewer shows from the scene folder and its store (through `wonderverse.schema`);
    WonderError, in one line, when there is no scene, no splat file or no posed camera. `splat_path`: a PLY in
    the frame of `world_from_sfm` to show instead of the folder's splat file (the studio's splats, written from
    the store as soon as the splats step has run); its name is the page's `splat`."""
    import numpy as np

    from flows.inspect import run_config
    from tasks.segments import attempt_path
    from wonderverse.camera import camera_centers
    from wonderverse.config import OutputsParams
    from wonderverse.paths import flythrough_path
    from wonderverse.schema import SFM, SPLATS
    from wonderverse.splats.web import Y_UP_FROM_WORLD
    from wonderverse.store import STORE_NAME, SceneStore

    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise WonderError(f"{scene_dir}: no such scene folder")
    if not (scene_dir / STORE_NAME).exists():
        raise WonderError(f"{scene_dir} holds no scene (no {STORE_NAME})")
    splat = next((name for name in SPLAT_FILES if (scene_dir / name).is_file()), None)
    if splat_path is not None:
        splat = Path(splat_path).name
    if splat is None:
        raise WonderError(f"{scene_dir} has no splats yet ({' or '.join(SPLAT_FILES)}): run the scene to `outputs`")
    store = SceneStore.open(scene_dir)
    if store.cache_key_of(SFM.path) is None:
        raise WonderError(f"{scene_dir} has no camera poses yet (step `poses`)")
    poses = store.array(SFM.poses)
    ok = np.isfinite(poses).all(axis=(1, 2))
    if not ok.any():
        raise WonderError(f"{scene_dir}: no frame has a camera pose")
    w2c, K = world_from_sfm(store).transform_w2c(poses[ok]), store.array(SFM.K)
    seg = store.meta(SFM.path).segments[int(store.array(SFM.frame_index)[np.argmax(ok), 0])]
    frames = store.open_array(attempt_path(store, seg).frames)
    height, width = (int(v) for v in frames.shape[1:3])
    cfg = run_config(store)
    outputs = cfg.steps.outputs if cfg is not None else OutputsParams()
    fly = flythrough_path(w2c, outputs.video_frames)
    splats = store.meta(SPLATS.path)
    background = tuple(float(c) for c in (splats.metrics.background_rgb if splats else None) or (0.0, 0.0, 0.0))
    look, size = _look_distance(Path(splat_path) if splat_path else scene_dir / splat, w2c[0], camera_centers(w2c))
    return SceneView(
        splat_file=splat,
        file_from_world=Y_UP_FROM_WORLD if splat.endswith(".spz") else np.eye(3),
        w2c=w2c,
        K=K,
        width=width,
        height=height,
        flythrough=fly,
        fps=outputs.video_fps,
        background=background,  # type: ignore[arg-type]
        look_distance=look,
        scene_size=size,
    )


def world_from_sfm(store: Any) -> Any:
    """The `camera.Sim3` from the global poses' frame (`sfm/`) to the frame the scene's files are in: what the
    outputs step recorded (`outputs` attrs `frame.world_from_sfm`), else the identity (the splats step's
    splats.ply was written in the `sfm/` frame)."""
    from wonderverse.camera import Sim3
    from wonderverse.schema import OUTPUTS

    outputs = store.meta(OUTPUTS.path)
    return Sim3.from_dict(outputs.frame.world_from_sfm) if outputs is not None else Sim3.identity()


def _look_distance(splat_path: Path, w2c0: np.ndarray, centres: np.ndarray) -> tuple[float, float]:
    """(median depth of the splat centres in front of the first camera, the size of the scene: the 98th
    percentile distance of the centres from the cameras' mean, at least the cameras' spread), world units."""
    import numpy as np

    from wonderverse.splats.ply import read_ply
    from wonderverse.splats.web import read_spz

    means = (read_spz(splat_path) if splat_path.suffix == ".spz" else read_ply(splat_path))["means"].astype(float)
    means = means[np.isfinite(means).all(axis=1)]
    spread = float(np.ptp(centres, axis=0).max()) if len(centres) > 1 else 0.0
    if not len(means):
        return max(spread, 1.0), max(spread, 1.0)
    z = means @ w2c0[2, :3] + w2c0[2, 3]
    size = max(float(np.percentile(np.linalg.norm(means - centres.mean(0), axis=1), 98)), spread, 1e-6)
    return (float(np.median(z[z > 0])) if (z > 0).any() else size), size


def scene_json(view: SceneView, studio: bool = False) -> str:
    """The scene as the page's JSON (three.js conventions: column-major C2W with OpenGL axes); `studio`: the
    page draws each training camera's frustum and, left idle, draws a frame every 2 s (the studio does: its jobs need
    the CPU; `view` keeps the picture of the splats alone, at full rate)."""
    import numpy as np

    K = view.K
    data = {
        "splat": view.splat_file,
        # three's Matrix4.fromArray is column-major: the mesh's matrix turns the file's axes into the world
        "splatMatrix": np.pad(view.file_from_world.T, ((0, 1), (0, 1))).T.reshape(-1).tolist(),
        "cameras": [_c2w_gl(p) for p in view.w2c],
        "flythrough": [_c2w_gl(p) for p in view.flythrough],
        "fps": view.fps,
        "K": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]},
        "width": view.width,
        "height": view.height,
        "background": list(view.background),
        "lookDistance": view.look_distance,
        "near": view.scene_size * 1e-4,
        "far": view.scene_size * 100.0,
        "showCameras": studio,
        "idleFps": 0.5 if studio else None,
    }
    data["splatMatrix"][15] = 1.0
    return json.dumps(data, separators=(",", ":")).replace("</", "<\\/")


APP_JS = r"""
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

const S = JSON.parse(document.getElementById("wv-scene").textContent);
const state = (window.wonderverse = { ready: false, frames: 0, error: null, camera: 0, playing: false });
state.matrix = () => camera.updateMatrixWorld() || camera.matrixWorld.toArray(); // column-major C2W, OpenGL axes
const canvas = document.getElementById("wv-canvas");
const status = document.getElementById("wv-status");
const say = (text) => (status.textContent = text);

const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
const background = new THREE.Color().setRGB(...S.background, THREE.SRGBColorSpace);
renderer.setClearColor(background, 1);
const scene = new THREE.Scene();
// Our renderer's conventions (wonderverse.splats.render_torch, gsplat 1.5.3 without antialiasing): sort by
// camera z, add 0.3 px^2 to the 2D covariance without compensating opacity, cut at 3 sigma, skip alpha < 1/255.
const spark = new SparkRenderer({
  renderer, sortRadial: false, preBlurAmount: 0.3, blurAmount: 0.0, maxStdDev: 3.0, minAlpha: 1.0 / 255.0,
  focalAdjustment: 1.0,
});
scene.add(spark);
const camera = new THREE.PerspectiveCamera();
camera.matrixAutoUpdate = true;
scene.add(camera);

// the projection of the training cameras' K (pixel centres at +0.5): the canvas keeps their aspect ratio
const K = S.K, W = S.width, H = S.height, n = S.near, f = S.far;
camera.projectionMatrix.set(
  2 * K.fx / W, 0, 1 - 2 * K.cx / W, 0,
  0, 2 * K.fy / H, 2 * K.cy / H - 1, 0,
  0, 0, -(f + n) / (f - n), -2 * f * n / (f - n),
  0, 0, -1, 0);
camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();

function fit() {
  const s = Math.min(window.innerWidth / W, window.innerHeight / H);
  const w = Math.max(1, Math.floor(W * s)), h = Math.max(1, Math.floor(H * s));
  renderer.setSize(w, h, true);
}
window.addEventListener("resize", fit);
fit();

const m = new THREE.Matrix4();
function place(c2w) {
  m.fromArray(c2w);
  m.decompose(camera.position, camera.quaternion, camera.scale);
  camera.updateMatrixWorld(true);
}
camera.up.set(0, 0, 1); // the world's up (+z): the orbit turns about it (OrbitControls reads it when made)
const controls = new OrbitControls(camera, canvas);
function aim(distance) {
  // orbit about the point the camera looks at; the controls act only when the user drags
  const forward = new THREE.Vector3(0, 0, -1).applyQuaternion(camera.quaternion);
  controls.target.copy(camera.position).addScaledVector(forward, distance);
}

const label = document.getElementById("wv-camera");
function goTo(k) {
  state.camera = (k + S.cameras.length) % S.cameras.length;
  place(S.cameras[state.camera]);
  aim(S.lookDistance);
  label.textContent = `camera ${state.camera + 1}/${S.cameras.length}`;
}
const hash = new URLSearchParams(location.hash.slice(1));
goTo(Number(hash.get("camera") || 0));
controls.saveState();

let t0 = null;
function play(on) {
  state.playing = on;
  controls.enabled = !on;
  document.getElementById("wv-play").textContent = on ? "■ stop" : "▶ fly-through";
  t0 = null;
  if (!on) {
    aim(S.lookDistance);
    label.textContent = `camera ${state.camera + 1}/${S.cameras.length} (fly-through stopped)`;
  }
}
document.getElementById("wv-play").onclick = () => play(!state.playing);
document.getElementById("wv-prev").onclick = () => { play(false); goTo(state.camera - 1); };
document.getElementById("wv-next").onclick = () => { play(false); goTo(state.camera + 1); };
window.addEventListener("keydown", (e) => {
  if (e.key === "[") document.getElementById("wv-prev").click();
  if (e.key === "]") document.getElementById("wv-next").click();
  if (e.key === "p") document.getElementById("wv-play").click();
});

if (S.showCameras) {
  // each training camera as a frustum of lines (apex at the centre, the image plane at 4 % of the scene's size)
  const d = 0.04 * S.lookDistance, points = [];
  const corners = [[0, 0], [W, 0], [W, H], [0, H]].map(([u, v]) =>
    new THREE.Vector3(((u - K.cx) / K.fx) * d, -((v - K.cy) / K.fy) * d, -d));
  for (const c2w of S.cameras) {
    const mc = new THREE.Matrix4().fromArray(c2w), o = new THREE.Vector3().applyMatrix4(mc);
    const q = corners.map((c) => c.clone().applyMatrix4(mc));
    for (let i = 0; i < 4; i++) points.push(o, q[i], q[i], q[(i + 1) % 4]);
  }
  const lines = new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(points),
    new THREE.LineBasicMaterial({ color: 0xffaa33 }));
  scene.add(lines);
}

function show(splat) {
  splat.matrixAutoUpdate = false;
  splat.matrix.fromArray(S.splatMatrix);
  splat.updateMatrixWorld(true);
  scene.add(splat);
  return splat.initialized.then(() => {
    say("");
    state.loaded = true;
  });
}

async function load() {
  say(`loading ${S.splat} …`);
  try {
    const response = await fetch(S.splat);
    if (!response.ok) throw new Error(`${S.splat}: HTTP ${response.status}`);
    const bytes = new Uint8Array(await response.arrayBuffer());
    await show(new SplatMesh({ fileBytes: bytes, fileName: S.splat }));
  } catch (err) {
    state.error = String(err);
    say(`${S.splat} could not be read beside this page (${err}); drop the file here to view it, or run ` +
        "`wonderverse view` on the scene folder");
  }
}
document.addEventListener("dragover", (e) => e.preventDefault());
document.addEventListener("drop", async (e) => {
  e.preventDefault();
  const file = e.dataTransfer.files[0];
  if (!file) return;
  state.error = null;
  await show(new SplatMesh({ fileBytes: new Uint8Array(await file.arrayBuffer()), fileName: file.name }));
});

// S.idleFps (the studio's view): once the splats have settled (10 frames drawn) and nobody has touched the page for
// 2 s, draw only idleFps frames a second, so an idle view leaves the CPU to the jobs (software WebGL draws on the
// CPU: a frame of a small scene took ~0.4 s of a core in headless Chromium on 2 cores)
let lastInput = -1e9, lastDraw = -1e9;
for (const type of ["pointerdown", "pointermove", "wheel", "keydown", "click"]) {
  window.addEventListener(type, () => (lastInput = performance.now()), { passive: true });
}
renderer.setAnimationLoop((time) => {
  const idle = !state.playing && state.frames >= 10 && time - lastInput > 2000;
  if (S.idleFps && idle && time - lastDraw < 1000 / S.idleFps) return;
  lastDraw = time;
  if (state.playing) {
    if (t0 === null) t0 = time;
    const i = Math.floor(((time - t0) / 1000) * S.fps) % S.flythrough.length;
    place(S.flythrough[i]);
    label.textContent = `fly-through ${i + 1}/${S.flythrough.length}`;
  }
  renderer.render(scene, camera);
  if (state.loaded) {
    state.frames += 1;
    if (state.frames >= 3) state.ready = true;
  }
});
load();
"""

PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<title>WonderVerse — {title}</title>
<style>
html, body {{ margin: 0; height: 100%; background: #111; overflow: hidden; font: 14px system-ui, sans-serif; }}
#wv-canvas {{ display: block; position: absolute; left: 50%; top: 50%; transform: translate(-50%, -50%); }}
#wv-bar {{ position: fixed; left: 8px; top: 8px; display: flex; gap: 6px; align-items: center; color: #eee;
  background: rgba(0,0,0,.55); padding: 4px 8px; border-radius: 6px; z-index: 1; }}
#wv-bar button {{ font: inherit; background: #333; color: #eee; border: 1px solid #666; border-radius: 4px; }}
#wv-status {{ position: fixed; left: 8px; bottom: 8px; right: 8px; color: #fc6; z-index: 1; }}
</style>
{modules}
</head>
<body>
<canvas id="wv-canvas"></canvas>
<div id="wv-bar"><button id="wv-prev" title="previous training camera ([)">◀</button>
<span id="wv-camera"></span><button id="wv-next" title="next training camera (])">▶</button>
<button id="wv-play" title="play the fly-through (p)">▶ fly-through</button>
<span title="drag: orbit, right-drag: pan, wheel: zoom">{title}</span></div>
<div id="wv-status"></div>
<script type="application/json" id="wv-scene">{scene}</script>
{app}
</body>
</html>
"""

# Inlined modules: each one's source is kept as text and loaded from a blob: URL; relative imports inside three's
# build (./three.core.js) are pointed at the blob of that file, bare ones ("three") resolve through an import map
# added before the first module loads.
INLINE_LOADER = """<script>
(() => {
  const text = (id) => document.getElementById(id).textContent;
  const url = (source) => URL.createObjectURL(new Blob([source], { type: "text/javascript" }));
  const blobs = {};
  blobs["three.core.js"] = url(text("wv-src-three.core.js"));
  for (const name of NAMES) {
    const source = text("wv-src-" + name).replaceAll("./three.core.js", blobs["three.core.js"]);
    if (name !== "three.core.js") blobs[name] = url(source);
  }
  const map = document.createElement("script");
  map.type = "importmap";
  const imports = Object.fromEntries(Object.entries(IMPORTS).map(([k, v]) => [k, blobs[v]]));
  map.textContent = JSON.stringify({ imports });
  document.head.appendChild(map);
  const app = document.createElement("script");
  app.type = "module";
  app.textContent = text("wv-app");
  document.body.appendChild(app);
})();
</script>"""


def _script_text(source: str) -> str:
    """JavaScript made safe inside a <script type="text/plain"> element (no closing tag can end it early)."""
    return source.replace("</script", "<\\/script").replace("<!--", "<\\!--")


def page_html(view: SceneView, title: str, inline: dict[str, bytes] | None = None, studio: bool = False) -> str:
    """The viewer page. `inline` None: the modules are imported from /_viewer/ (the server's page); else the
    files of `viewer_files()` are inlined and loaded from blob URLs (the self-contained viewer.html).
    `studio`: as `scene_json`."""
    title = html.escape(title)
    if inline is None:
        imports = {k: f"/_viewer/{v}" for k, v in IMPORTS.items()}
        modules = f'<script type="importmap">{json.dumps({"imports": imports})}</script>'
        app = f'<script type="module">{APP_JS}</script>'
    else:
        sources = [
            f'<script type="text/plain" id="wv-src-{name}">{_script_text(data.decode("utf-8"))}</script>'
            for name, data in inline.items()
        ]
        loader = INLINE_LOADER.replace("NAMES", json.dumps(list(inline))).replace("IMPORTS", json.dumps(IMPORTS))
        modules = ""
        app = "\n".join([*sources, f'<script type="text/plain" id="wv-app">{_script_text(APP_JS)}</script>', loader])
    return PAGE.format(title=title, modules=modules, scene=scene_json(view, studio), app=app)


def write_viewer_html(scene_dir: Path, view: SceneView, files: dict[str, bytes]) -> Path:
    """Write SCENE_DIR/viewer.html (self-contained but for the splat file beside it) atomically; WonderError
    when the scene folder cannot be written."""
    path = Path(scene_dir) / VIEWER_HTML
    tmp = path.with_name(f".{VIEWER_HTML}.{os.getpid()}.tmp")
    try:
        tmp.write_text(page_html(view, Path(scene_dir).resolve().name, inline=files), encoding="utf-8")
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise WonderError(
            f"cannot write {VIEWER_HTML} into {scene_dir}: {e.strerror or e} (view writes the viewer beside the "
            "splats; copy the scene to a writable folder)"
        ) from None
    return path


def scene_file(scene_dir: Path, url_path: str) -> Path | None:
    """The regular file inside `scene_dir` that `url_path` (the URL's path, still %-encoded) names, or None:
    no `..`, no absolute or drive paths, no backslashes or NUL, no hidden components, and the resolved path
    (symlinks followed) must stay inside the resolved scene folder."""
    raw = unquote(url_path)
    if "\\" in raw or "\0" in raw or not raw.startswith("/"):
        return None
    parts = [p for p in raw.split("/") if p]
    if not parts or any(p in (".", "..") or p.startswith(".") or ":" in p for p in parts):
        return None
    root = Path(scene_dir).resolve()
    try:
        path = root.joinpath(*parts).resolve(strict=True)
    except (OSError, RuntimeError):
        return None
    return path if path.is_file() and path.is_relative_to(root) else None


def make_server(scene_dir: Path, view: SceneView, files: dict[str, bytes], host: str, port: int) -> ThreadingHTTPServer:
    """The viewer's HTTP server (not started); WonderError when the address cannot be bound."""
    import socket
    from http import HTTPStatus
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    title = Path(scene_dir).resolve().name
    index = page_html(view, title).encode()

    class Handler(BaseHTTPRequestHandler):
        server_version = "WonderVerse-view"

        def log_message(self, format: str, *args: Any) -> None:  # quiet: the terminal shows the one URL line
            pass

        def _send(self, status: int, body: bytes, ctype: str, head: bool) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            if not head:
                self.wfile.write(body)

        def _file(self, path: Path, head: bool) -> None:
            ctype = CONTENT_TYPES.get(path.suffix.lower(), "application/octet-stream")
            size = path.stat().st_size
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(size))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.end_headers()
            if not head:
                with path.open("rb") as f:
                    while chunk := f.read(1 << 20):
                        self.wfile.write(chunk)

        def _serve(self, head: bool) -> None:
            path = urlsplit(self.path).path
            if path in ("/", "/index.html"):
                return self._send(HTTPStatus.OK, index, CONTENT_TYPES[".html"], head)
            if path.startswith("/_viewer/") and path[len("/_viewer/") :] in files:
                return self._send(HTTPStatus.OK, files[path[len("/_viewer/") :]], CONTENT_TYPES[".js"], head)
            found = scene_file(scene_dir, path)
            if found is None:
                return self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain", head)
            return self._file(found, head)

        def do_GET(self) -> None:
            with contextlib.suppress(BrokenPipeError, ConnectionResetError):
                self._serve(head=False)

        def do_HEAD(self) -> None:
            with contextlib.suppress(BrokenPipeError, ConnectionResetError):
                self._serve(head=True)

    class Server(ThreadingHTTPServer):
        daemon_threads = True
        allow_reuse_address = False  # a port in use is refused, never shared
        address_family = socket.AF_INET6 if ":" in host else socket.AF_INET

    try:
        return Server((host, port), Handler)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise WonderError(f"port {port} on {host} is in use: choose another with --port, or leave it out") from None
        raise WonderError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None


def serve_scene(scene_dir: Path, host: str = "127.0.0.1", port: int = 0) -> None:
    """Check the scene, write viewer.html, then serve until the process is stopped (Ctrl-C: the supervisor
    kills it). Prints one line with the address."""
    scene_dir = Path(scene_dir)
    view = scene_view(scene_dir)
    files = viewer_files()
    server = make_server(scene_dir, view, files, host, port)
    try:
        written = write_viewer_html(scene_dir, view, files)
        bound_host, bound_port = server.server_address[:2]
        shown = f"[{bound_host}]" if ":" in str(bound_host) else bound_host
        print(
            f"viewing {scene_dir} ({view.splat_file}, {len(view.w2c)} cameras) at http://{shown}:{bound_port}/ "
            f"— Ctrl-C stops; {written} opens it without a server",
            flush=True,
        )
        server.serve_forever()
    finally:
        server.server_close()


def view_command(
    scene_dir: Annotated[Path, typer.Argument(help="scene folder with splats (splats.spz or splats.ply)")],
    port: Annotated[int, typer.Option(help="port (default: a free one)", min=0, max=65535)] = 0,
    host: Annotated[str, typer.Option(help="address to bind (default 127.0.0.1: this machine only)")] = "127.0.0.1",
) -> None:
    """Serve the scene in a real-time splat viewer (Spark) in the browser; writes SCENE_DIR/viewer.html."""
    if host not in ("127.0.0.1", "localhost", "::1"):
        print(f"wonderverse: serving on {host}: other machines on that network can see the scene", file=sys.stderr)
    serve_scene(scene_dir, host, port)
