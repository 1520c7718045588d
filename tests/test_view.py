"""`wonderverse view`: a small real scene (the pipeline to `splats`) served and rendered by Spark in headless
Chromium (SwiftShader) matches our own renderer's image of the same training camera; the server serves nothing
outside the scene; bad input is one `error:` line; Ctrl-C stops the server with the command.

Ground truth: `render_views` of the stored Gaussians from the stored cameras (our renderer), the scene folder's
own files, and the OS (whether the port still accepts connections, whether the process is alive).
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, launch_browser, run_cli
from PIL import Image

from flows.pipeline import execute
from flows.view import VIEWER_HTML, scene_file, scene_json, scene_view
from wonderverse.config import build_config
from wonderverse.schema import SPLATS
from wonderverse.store import SceneStore

MIN_PSNR_DB = 25.0
READY = "window.wonderverse && (window.wonderverse.ready || window.wonderverse.error)"
CANVAS_PNG = "document.getElementById('wv-canvas').toDataURL('image/png')"


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """One procedural segment at 160x112, 8 frames, through `outputs` (splats.ply in the outputs' world frame)
    with 80 splat iterations and 8-frame videos."""
    outputs = {"video_frames": 8, "colmap": False, "nerfstudio": False, "quality_frames": 1}
    cfg = build_config(
        "a small house decorated for Christmas",
        preset="preview",
        overrides={
            "scene": {
                "video": {"width": 160, "height": 112, "frames_per_segment": 8, "options": {"fault_probability": 0.0}},
                "extensions": {"rounds": 0},
            },
            "steps": {
                "check": {"sfm": {"min_points": 40}},
                "splats": {"max_side_px": 160, "train": {"iterations": 80}},
                "outputs": {**outputs, "mesh": {"extra_views_per_gap": 0}},
            },
            "execution": {"segment_workers": 1, "renderer": "torch"},
        },
    )
    folder = tmp_path_factory.mktemp("view") / "scene"
    results = execute(folder, cfg, until="outputs")
    assert all(r.status == "ran" for r in results)
    assert (folder / "splats.ply").is_file() and (folder / "splats.spz").is_file()
    # The viewer prefers splats.spz; most tests here view the PLY (the SPZ has its own test on a copy)
    (folder / "splats.spz").unlink()
    return folder


def _our_render(scene_dir: Path, camera: int) -> np.ndarray:
    """Our renderer's image (H,W,3) uint8 of the `camera`-th posed training camera, straight from the store (the
    `sfm/` poses and the splats' own normalisation: no output frame involved), with the learned background."""
    from wonderverse.schema import SFM
    from wonderverse.splats.model import GaussianModel, normalization_from_dict
    from wonderverse.splats.renderer import make_renderer
    from wonderverse.splats.views import render_views

    view = scene_view(scene_dir)
    store = SceneStore.open(scene_dir)
    poses = store.array(SFM.poses)
    poses = poses[np.isfinite(poses).all(axis=(1, 2))]
    splats = store.meta(SPLATS.path)
    arrays = {name: store.array(getattr(SPLATS, name)) for name in GaussianModel.PARAM_NAMES}
    rgb = next(
        render_views(
            arrays,
            normalization_from_dict(splats.normalization),
            poses[camera : camera + 1],
            store.array(SFM.K),
            view.width,
            view.height,
            make_renderer("torch"),
            background=splats.metrics.background_rgb,
        )
    ).rgb
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def _settled_canvas(page, timeout_s: float = 60.0) -> np.ndarray:
    """The canvas once the splats are loaded and two frames 0.4 s apart are identical (Spark sorts in a worker)."""
    page.wait_for_function(READY, timeout=timeout_s * 1000)
    state = page.evaluate("({ready: window.wonderverse.ready, error: window.wonderverse.error})")
    assert state["ready"], state
    previous, deadline = None, time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        data = page.evaluate(CANVAS_PNG)
        if data == previous:
            break
        previous = data
        time.sleep(0.4)
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(data.split(",", 1)[1]))).convert("RGB"))


@contextmanager
def _viewing(scene_dir: Path, *args: str) -> Iterator[tuple[subprocess.Popen, str]]:
    """`wonderverse view SCENE ARGS` as a user runs it (supervised); yields (process, URL); Ctrl-C at the end."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "flows", "view", str(scene_dir), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        line = proc.stdout.readline()
        assert line.startswith("viewing "), (line, proc.stderr.read() if proc.poll() is not None else "")
        yield proc, line.split(" at ", 1)[1].split()[0]
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        proc.wait(timeout=20)


def _playwright():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        if os.environ.get("WONDERVERSE_ALLOW_NO_BROWSER") == "1":
            pytest.skip("playwright is not installed")
        pytest.fail("the playwright package is missing: pip install playwright")
    return sync_playwright()


def _page(browser, view, log: list[str], requests: list[str]):
    page = browser.new_page(viewport={"width": view.width, "height": view.height})
    page.on("console", lambda m: log.append(f"{m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: log.append(f"page error: {e}"))
    page.on("request", lambda r: requests.append(r.url))
    return page


# ------------------------------------------------------------------------------------------- conventions


def test_three_camera_matrix_is_the_opencv_pose_with_y_and_z_flipped():
    """A camera at (1, 2, 3) looking along world +x with image-down along world -z: three's camera looks down its
    -z (world +x), its +y is image-up (world +z), its +x is image-right (world -y)."""
    from flows.view import _c2w_gl
    from wonderverse.camera import look_at

    w2c = look_at(np.array([1.0, 2.0, 3.0]), np.array([5.0, 2.0, 3.0]), np.array([0.0, 0.0, 1.0]))
    m = np.array(_c2w_gl(w2c)).reshape(4, 4).T  # column-major -> matrix
    np.testing.assert_allclose(m[:3, 3], [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(m[:3, :3] @ [0, 0, -1], [1, 0, 0], atol=1e-12)  # forward
    np.testing.assert_allclose(m[:3, :3] @ [0, 1, 0], [0, 0, 1], atol=1e-12)  # up
    np.testing.assert_allclose(m[:3, :3] @ [1, 0, 0], [0, -1, 0], atol=1e-12)  # right


def test_only_files_inside_the_scene_are_served(tmp_path: Path):
    scene_dir = tmp_path / "scene"
    (scene_dir / "sub").mkdir(parents=True)
    (scene_dir / "splats.ply").write_bytes(b"ply")
    (scene_dir / "sub" / "a.png").write_bytes(b"png")
    (scene_dir / ".wonderverse.lock").write_bytes(b"")
    (tmp_path / "secret.txt").write_text("secret")
    (scene_dir / "link").symlink_to(tmp_path / "secret.txt")
    (scene_dir / "dirlink").symlink_to(tmp_path)
    assert scene_file(scene_dir, "/splats.ply") == (scene_dir / "splats.ply").resolve()
    assert scene_file(scene_dir, "/sub/a.png") == (scene_dir / "sub" / "a.png").resolve()
    assert scene_file(scene_dir, "/sub%2Fa.png") == (scene_dir / "sub" / "a.png").resolve()
    refused = [
        "/../secret.txt",
        "/sub/../../secret.txt",
        "/%2e%2e/secret.txt",
        "/%2E%2E%2Fsecret.txt",
        "/..%5csecret.txt",
        "/sub\\..\\..\\secret.txt",
        "//" + str(tmp_path / "secret.txt"),
        str(tmp_path / "secret.txt"),
        "/" + str(tmp_path / "secret.txt").lstrip("/"),
        "/link",
        "/dirlink/secret.txt",
        "/.wonderverse.lock",
        "/splats.ply%00.png",
        "/C:/secret.txt",
        "/sub",
        "/",
        "relative.txt",
        "/missing.ply",
    ]
    assert {p: scene_file(scene_dir, p) for p in refused} == dict.fromkeys(refused)


# ------------------------------------------------------------------------------------------- bad input


@pytest.mark.e2e
def test_a_folder_without_splats_or_without_a_scene_is_one_error_line(tmp_path: Path):
    (tmp_path / "empty" / "scene.zarr").mkdir(parents=True)
    for folder, words in [
        (tmp_path / "empty", "has no splats yet"),
        (tmp_path / "missing", "no such scene folder"),
        (tmp_path, "holds no scene"),
    ]:
        r = run_cli("view", str(folder), timeout=60)
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and words in lines[0], r.stderr
        assert not (folder / VIEWER_HTML).exists()


@pytest.mark.e2e
def test_a_busy_port_is_one_error_line(scene: Path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        r = run_cli("view", str(scene), "--port", str(port), timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"error: port {port} on 127.0.0.1 is in use: choose another with --port, or leave it out"
    ]


@pytest.mark.e2e
def test_a_read_only_scene_is_one_error_line(scene: Path, tmp_path: Path):
    copy = tmp_path / "ro"
    shutil.copytree(scene, copy, ignore=shutil.ignore_patterns(VIEWER_HTML))
    if os.geteuid() == 0:  # root writes through permission bits: make the folder immutable instead
        if subprocess.run(["chattr", "+i", str(copy)], capture_output=True).returncode != 0:
            pytest.skip("chattr +i is not available here (root ignores permission bits)")
        undo = ["chattr", "-i", str(copy)]
    else:
        copy.chmod(0o555)
        undo = ["chmod", "755", str(copy)]
    try:
        r = run_cli("view", str(copy), timeout=60)
    finally:
        subprocess.run(undo, check=True)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: cannot write {VIEWER_HTML} into {copy}"), r.stderr
    assert not (copy / VIEWER_HTML).exists()


def test_the_viewer_ships_in_the_package_and_its_absence_is_one_error(monkeypatch, tmp_path: Path):
    """The viewer's files are the package's own (no tools/node_modules, no npm): each is a real ES module of the
    right library, with both licences beside them, and pyproject declares them as package data. A package
    installed without them names the missing file and how to reinstall."""
    import tomllib

    import flows.view
    from wonderverse.errors import WonderError

    files = flows.view.viewer_files()
    assert set(files) == set(flows.view.VIEWER_FILES)
    for rel in flows.view.VIEWER_FILES.values():
        assert (ROOT / "flows" / "viewer_assets" / rel).is_file() and "node_modules" not in Path(rel).parts
    assert b"REVISION = '187'" in files["three.core.js"]  # three.js r187 = 0.187.0
    assert b"SplatMesh" in files["spark.module.js"]  # decompressed from the .gz the package holds
    for licence in ("LICENSE.three", "LICENSE.spark"):
        assert "MIT License" in (ROOT / "flows" / "viewer_assets" / licence).read_text()
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["flows"]
    for name in [*flows.view.VIEWER_FILES.values(), "LICENSE.three"]:
        assert any(Path("viewer_assets", name).match(pattern) for pattern in declared), name

    monkeypatch.setattr(flows.view, "VIEWER_ASSETS", tmp_path / "viewer_assets")
    with pytest.raises(WonderError, match=r"splat viewer is not installed \(.*three.core.js is missing\).*pip install"):
        flows.view.viewer_files()


# ------------------------------------------------------------------------------------------- the viewer


@pytest.mark.e2e
def test_spark_renders_the_training_cameras_as_our_renderer_does(scene: Path):
    """The served page opens at the first camera; `#camera=K` at camera K; each canvas is within MIN_PSNR_DB of
    our renderer. Nothing is fetched from anywhere but the server. The fly-through plays the outputs' path."""
    view = scene_view(scene)
    assert view.splat_file == "splats.ply"
    data = json.loads(scene_json(view))
    middle = len(view.w2c) // 2
    log: list[str] = []
    requests: list[str] = []
    measured = {}
    with _viewing(scene) as (proc, url), _playwright() as pw:
        assert url.startswith("http://127.0.0.1:")
        browser = launch_browser(pw)
        try:
            page = _page(browser, view, log, requests)
            page.goto(url)
            measured[0] = _psnr(_settled_canvas(page), _our_render(scene, 0))
            np.testing.assert_allclose(page.evaluate("window.wonderverse.matrix()"), data["cameras"][0], atol=1e-5)
            page.goto(f"{url}#camera={middle}")
            page.reload()
            measured[middle] = _psnr(_settled_canvas(page), _our_render(scene, middle))
            # the fly-through: the camera moves along the path's poses
            page.click("#wv-play")
            page.wait_for_timeout(1500)
            at = np.array(page.evaluate("window.wonderverse.matrix()"))
            assert page.evaluate("window.wonderverse.playing")
            assert np.abs(np.array(data["flythrough"]) - at).max(axis=1).min() < 1e-4
            page.click("#wv-play")
            assert not page.evaluate("window.wonderverse.playing")
            # a sideways drag orbits about the world's up (+z): the camera moves round at the same height
            before = np.array(page.evaluate("window.wonderverse.matrix()"))
            box = page.locator("#wv-canvas").bounding_box()
            x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] * 0.75  # below the button bar
            page.mouse.move(x, y)
            page.mouse.down()
            page.mouse.move(x + 40, y, steps=5)
            page.mouse.up()
            after = np.array(page.evaluate("window.wonderverse.matrix()"))
            assert np.linalg.norm(after[12:14] - before[12:14]) > 0.01 * view.scene_size
            assert after[14] == pytest.approx(before[14], abs=1e-4 * view.scene_size)
        finally:
            browser.close()
    assert proc.returncode == 130
    print(f"viewer vs renderer PSNR (dB): {measured}")
    assert all(v >= MIN_PSNR_DB for v in measured.values()), measured
    assert log == []
    fetched = [r for r in requests if not r.startswith("blob:")]  # Spark's workers start from blob: URLs
    assert {r.split("/")[2] for r in fetched} == {url.split("/")[2]}, "only the scene's server"
    paths = {r.split(url.split("/")[2], 1)[1].split("#")[0] for r in fetched}
    assert paths == {"/", "/splats.ply"} | {f"/_viewer/{name}" for name in flows_view_files()}


def flows_view_files() -> list[str]:
    from flows.view import VIEWER_FILES

    return list(VIEWER_FILES)


@pytest.mark.e2e
def test_the_spz_is_viewed_in_place_of_the_ply_with_the_same_picture(scene: Path, tmp_path: Path):
    from wonderverse.splats.ply import read_ply
    from wonderverse.splats.web import write_spz

    copy = tmp_path / "spz"
    shutil.copytree(scene, copy, ignore=shutil.ignore_patterns(VIEWER_HTML))
    write_spz(copy / "splats.spz", read_ply(copy / "splats.ply"))
    view = scene_view(copy)
    assert view.splat_file == "splats.spz"
    log: list[str] = []
    requests: list[str] = []
    with _viewing(copy) as (_, url), _playwright() as pw:
        browser = launch_browser(pw)
        try:
            page = _page(browser, view, log, requests)
            page.goto(url)
            psnr = _psnr(_settled_canvas(page), _our_render(copy, 0))
        finally:
            browser.close()
    print(f"viewer (SPZ) vs renderer PSNR: {psnr:.2f} dB")
    assert psnr >= MIN_PSNR_DB
    assert log == [] and any(r.endswith("/splats.spz") for r in requests)
    assert not any(r.endswith("/splats.ply") for r in requests)


@pytest.mark.e2e
def test_viewer_html_is_self_contained_and_takes_a_dropped_file_from_disk(scene: Path):
    """viewer.html (written by view) from a web server fetches only the splat file beside it; opened from disk
    it says the file cannot be read beside it, then shows the scene when the file is dropped on it."""
    view = scene_view(scene)
    with _viewing(scene) as (_, url), _playwright() as pw:
        html = (scene / VIEWER_HTML).read_text()
        browser = launch_browser(pw)
        try:
            log: list[str] = []
            requests: list[str] = []
            page = _page(browser, view, log, requests)
            page.goto(url + VIEWER_HTML)
            served = _settled_canvas(page)
            assert log == []
            fetched = [r for r in requests if not r.startswith("blob:")]
            assert fetched == [url + VIEWER_HTML, url + "splats.ply"]

            log, requests = [], []
            page = _page(browser, view, log, requests)
            page.goto((scene / VIEWER_HTML).as_uri())
            page.wait_for_function(READY, timeout=60_000)
            assert "drop the file here" in page.inner_text("#wv-status")
            payload = base64.b64encode((scene / "splats.ply").read_bytes()).decode()
            transfer = page.evaluate_handle(
                """(b64) => { const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
                   const dt = new DataTransfer(); dt.items.add(new File([bytes], "splats.ply")); return dt; }""",
                payload,
            )
            page.dispatch_event("body", "drop", {"dataTransfer": transfer})
            dropped = _settled_canvas(page)
        finally:
            browser.close()
    assert len(html) > 3_000_000 and "https://" not in html.split('id="wv-scene"')[0]
    assert "<script src=" not in html and 'type="importmap"' not in html.split("<body>")[0]
    assert _psnr(served, _our_render(scene, 0)) >= MIN_PSNR_DB
    assert _psnr(dropped, served) >= 40.0


@pytest.mark.e2e
def test_ctrl_c_stops_the_server_and_its_process(scene: Path):
    import psutil

    with _viewing(scene, "--port", "0") as (proc, url):
        port = int(url.rsplit(":", 1)[1].strip("/"))
        children = psutil.Process(proc.pid).children(recursive=True)
        assert children, "the command runs in a supervised child"
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 130
    time.sleep(0.2)
    assert not any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in children)
    with pytest.raises(OSError), socket.create_connection(("127.0.0.1", port), timeout=2):
        pass
