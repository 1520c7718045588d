"""The scene report: built from real (tiny) procedural scenes run through the pipeline, checked as HTML
(every segment and attempt, escaped user text, inlined images, only local links, the scene's videos and
mesh pictures) and rendered in headless Chromium (no console errors, every image decoded, both videos
load and decode a frame, a full-page screenshot of the expected size); rewritten only when the store changed.

Ground truth: the procedural world's injected faults (a scene seed is chosen so that exactly segment s000's
first attempt has a camera teleport), the files and videos we create, the config's video settings, and the
store's own listing."""

from __future__ import annotations

import base64
import html
import io
import os
import re
import shutil
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_VIDEO, launch_browser, tiny_config
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from flows.inspect import summarize
from flows.pipeline import execute
from flows.report import report_state, write_report
from flows.report_cache import CACHE_DIR
from tasks import STEPS
from tasks.segments import attempt_ids, segment_ids
from wonderverse.camera import Sim3
from wonderverse.config import build_config
from wonderverse.errors import WonderError
from wonderverse.media import write_mp4
from wonderverse.report import (
    AttemptInfo,
    FileEntry,
    ReportContent,
    SegmentInfo,
    StepTiming,
    colorize_depth,
    colorize_normals,
    fmt_bytes,
    image_size,
    render_html,
    video_stills,
)
from wonderverse.store import SceneStore
from wonderverse.video.procedural import ProceduralOptions, draw_fault
from wonderverse.video.prompts import attempt_seed

VIEWPORT = {"width": 1280, "height": 900}
VIDEOS = ("novel.mp4", "flythrough.mp4")
PROMPT = 'a snowy village <script>alert("x")</script> & <b>lanterns</b>'
# A long jump: on 6-frame segments a short one can hide in the median step (measured 3.4x for 1.7 m).
FAULTS = {"fault_probability": 0.5, "fault_types": ["teleport"], "teleport_m": [3.0, 4.0]}


# Resolves, per video, whether seeking to its middle ends with a decoded frame (readyState >= 2) within 10 s.
SEEK_AND_DECODE = """() => Promise.all(Array.from(document.querySelectorAll('video')).map(v => new Promise(done => {
    const timer = setTimeout(() => done(false), 10000);
    v.addEventListener('seeked', () => { clearTimeout(timer); done(v.readyState >= 2); }, {once: true});
    v.currentTime = v.duration / 2;
})))"""


class Page(HTMLParser):
    """Every tag's attributes, the text of elements by id, and all text."""

    def __init__(self, text: str):
        super().__init__()
        self.tags: list[tuple[str, dict[str, str | None]]] = []
        self.text: list[str] = []
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data):
        self.text.append(data)

    def attrs_of(self, tag: str) -> list[dict[str, str | None]]:
        return [a for t, a in self.tags if t == tag]


def seed_with_one_fault(frames: int) -> int:
    """A scene seed whose draws give s000 attempt 0 a fault and s000 attempt 1, s001, s002 none."""
    opts = ProceduralOptions(**FAULTS)
    want = {("s000", 0): True, ("s000", 1): False, ("s001", 0): False, ("s002", 0): False}
    for seed in range(500):
        draws = {(s, k): draw_fault(seed, attempt_seed(seed, s, k), frames, opts) for s, k in want}
        if all((draws[key] is not None) == v for key, v in want.items()):
            return seed
    raise AssertionError("no scene seed with the wanted faults")


@pytest.fixture(scope="module")
def full_scene(tmp_path_factory) -> Path:
    """3 segments (one regenerated after a teleport) through every step, splats kept tiny (~20 s)."""
    seed = seed_with_one_fault(TINY_VIDEO["frames_per_segment"])
    cfg = build_config(
        PROMPT,
        preset="preview",
        overrides={
            "scene": {"seed": seed, "video": {**TINY_VIDEO, "options": FAULTS}},
            "steps": {
                # in-process (no Dask cluster start-up); tiny frames give fewer SfM points than the default gate
                "check": {"max_attempts": 2, "sfm": {"min_points": 40}},
                "splats": {"max_side_px": 48, "train": {"iterations": 10, "holdout_every": 4}},
            },
            "execution": {"segment_workers": 1, "renderer": "torch"},
        },
    )
    scene = tmp_path_factory.mktemp("report") / "scene"
    results = execute(scene, cfg)
    assert [r.status for r in results] == ["ran"] * len(STEPS)
    check = SceneStore.open(scene).meta("segments/s000/attempts/0/check")
    assert not check.accepted, "precondition: the teleport attempt is rejected"
    write_report(scene)
    return scene


@pytest.fixture(scope="module")
def partial_scene(tmp_path_factory) -> Path:
    """One segment, run only up to generate_segments."""
    scene = tmp_path_factory.mktemp("report") / "partial"
    execute(scene, tiny_config(extensions={"rounds": 0}), until="generate_segments")
    return scene


def row(text: str, row_id: str) -> str:
    m = re.search(rf'<tr id="{row_id}">(.*?)</tr>', text, re.S)
    assert m, f"no table row {row_id}"
    return m.group(1)


def section(text: str, sid: str) -> str:
    m = re.search(rf'<section id="{sid}">(.*?)</section>', text, re.S)
    assert m, f"no section {sid}"
    return m.group(1)


def assert_self_contained(text: str, scene: Path) -> Page:
    """Images are decodable data URIs of the size they declare; links and videos are in-page or existing
    local files beside the report."""
    page = Page(text)
    assert not re.search(r"https?://", text)
    assert not page.attrs_of("script") and "<script" not in text.lower()
    for a in page.attrs_of("img"):
        src = a["src"] or ""
        assert src.startswith("data:image/png;base64,"), src[:40]
        img = Image.open(io.BytesIO(base64.b64decode(src.split(",", 1)[1])))
        assert img.size == (int(a["width"]), int(a["height"]))
    for a in page.attrs_of("a"):
        href = a["href"] or ""
        assert href.startswith("#") or (scene / href).exists(), href
        if href.startswith("#"):
            assert f'id="{href[1:]}"' in text, f"dangling in-page link {href}"
    for a in page.attrs_of("link"):
        assert (a["href"] or "").startswith("data:")
    for a in page.attrs_of("video"):
        assert "/" not in (a["src"] or "/") and (scene / a["src"]).is_file(), a["src"]
    return page


def png_pixels(img_tag_attrs: dict[str, str | None]) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(base64.b64decode((img_tag_attrs["src"] or "").split(",", 1)[1]))))


# -- library ------------------------------------------------------------------------------------


def test_image_size_reads_png_and_jpeg_headers():
    for fmt, mime in (("PNG", "image/png"), ("JPEG", "image/jpeg")):
        buf = io.BytesIO()
        Image.new("RGB", (37, 21), (10, 200, 30)).save(buf, format=fmt)
        assert image_size(buf.getvalue()) == (mime, 37, 21)
    with pytest.raises(ValueError):
        image_size(b"GIF89a....")


@settings(max_examples=60, deadline=None)
@given(st.integers(1_000_000, 999_949_999))
def test_sizes_are_decimal_as_inspect_prints_them(n):
    assert fmt_bytes(n) == f"{n / 1e6:.1f} MB"  # how `wonderverse inspect` prints sizes


def test_size_units():
    assert [fmt_bytes(n) for n in (0, 999, 1000, 1499, 999_949, 999_950, 2_500_000_000)] == [
        "0 B", "999 B", "1.0 kB", "1.5 kB", "999.9 kB", "1.0 MB", "2.5 GB",
    ]  # fmt: skip


def test_video_stills_are_the_evenly_spaced_frames(tmp_path: Path):
    grey = (np.arange(12) * 20).astype(np.uint8)  # frame i is uniformly 20 * i
    frames = np.broadcast_to(grey[:, None, None, None], (12, 24, 32, 3)).copy()
    path = write_mp4(frames, tmp_path / "v.mp4", fps=6)
    stills, idx, n, seconds = video_stills(path, 4)
    assert idx == [0, 4, 7, 11] and n == 12 and abs(seconds - 2.0) < 0.2  # round(linspace(0, 11, 4))
    assert stills.shape == (4, 24, 32, 3) and stills.dtype == np.uint8
    np.testing.assert_allclose(stills.reshape(4, -1).mean(axis=1), grey[idx], atol=4)
    everything, idx_all, _, _ = video_stills(path, 50)  # more asked than there are: every frame once
    assert idx_all == list(range(12)) and len(everything) == 12
    (tmp_path / "bad.mp4").write_bytes(b"not a video")
    with pytest.raises((OSError, RuntimeError, ValueError)):
        video_stills(tmp_path / "bad.mp4", 4)


def test_depth_and_normal_colours():
    depth = np.array([[1.0, 2.0, 4.0, np.inf]])
    rgb = colorize_depth(depth)
    assert (rgb[0, 3] == 40).all()  # sky: dark grey
    # turbo runs blue (far, small inverse depth) to red (near)
    assert rgb[0, 0, 0] > rgb[0, 0, 2] and rgb[0, 2, 2] > rgb[0, 2, 0]
    n = np.array([[[0, 0, -1], [0, -1, 0], [0, 0, 0]]], float)  # facing the camera, up (OpenCV), missing
    np.testing.assert_array_equal(colorize_normals(n)[0], [[128, 128, 255], [128, 255, 128], [128, 128, 128]])


@settings(max_examples=40, deadline=None)
@given(st.text(min_size=1, max_size=60), st.text(max_size=40), st.text(max_size=30))
def test_user_text_is_escaped_everywhere(prompt, reason, intent):
    content = ReportContent(
        title=f"report {intent}",
        prompt=prompt,
        facts={"seed": 3, intent or "x": reason},
        segments=[
            SegmentInfo(id="s000", role="init", move=intent, intent=intent, attempts=[AttemptInfo(0, reasons=[reason])])
        ],
        timings=[StepTiming("plan", "complete", 1.5, intent)],
        metrics={intent or "m": {reason or "r": 1.0}},
        files=[FileEntry(f'a "{intent}".ply', 10)],
        notes=[reason],
    )
    text = render_html(content)
    page = Page(text)
    # the only tags are ours: user text never opens one
    assert {t for t, _ in page.tags} <= {
        "html", "head", "meta", "link", "title", "style", "body", "header", "h1", "div", "nav", "a", "main",
        "blockquote", "section", "h2", "h3", "h4", "table", "tr", "th", "td", "p", "span", "ul", "li", "i", "footer",
    }  # fmt: skip
    quote = re.search(r'<blockquote class="prompt">(.*?)</blockquote>', text, re.S).group(1)
    assert html.unescape(quote) == prompt


# -- the report of a real scene -----------------------------------------------------------------


@pytest.mark.e2e
def test_report_lists_every_segment_and_attempt_with_its_verdict(full_scene: Path):
    text = (full_scene / "report.html").read_text()
    store = SceneStore.open(full_scene)
    segs = segment_ids(store)
    assert segs == ["s000", "s001", "s002"]
    for seg in segs:
        assert f'id="seg-{seg}"' in text
        for k in attempt_ids(store, seg):
            row(text, f"{seg}-a{k}")
    assert len(re.findall(r'<tr id="s\d+-a\d+">', text)) == 4  # s000 twice, the others once
    # the injected teleport: attempt 0 rejected (with the check's words), attempt 1 accepted and used
    bad, good = row(text, "s000-a0"), row(text, "s000-a1")
    assert "rejected" in bad and "teleport at frame" in bad and "translation" in bad and "used" not in bad
    assert "accepted" in good and ">used<" in good and "none" in good
    assert "attempt 1 accepted" in text
    # one check plot and one top view per attempt, a depth/normal preview per segment
    segments = section(text, "segments")
    assert segments.count("steps against the thresholds") == 4 * 2  # alt text + caption
    assert segments.count("camera path from above</figcaption>") == 4
    assert segments.count("normal priors") >= 3


@pytest.mark.e2e
def test_a_generated_scene_has_its_plan_and_priors_and_no_clips(full_scene: Path):
    text = (full_scene / "report.html").read_text()
    assert '<section id="plan">' in text and '<section id="clips">' not in text
    assert "No depth or normal previews" not in text and "<th>priors</th>" not in section(text, "summary")
    info = summarize(SceneStore.open(full_scene))
    assert info["clips"] is None
    # the procedural world's default priors: the oracle depth, normals from it
    sky = info["priors"].pop("sky_share")
    assert 0.0 < sky < 0.6  # an outdoor village under the sky; the share is the truth's in test_outputs
    assert info["priors"] == {
        "depth_backend": "oracle",
        "normal_backend": "from_depth",
        "computed": True,
        "words": f"depth oracle, normals from_depth; {100 * sky:.1f} % of pixels sky",
    }


@pytest.mark.e2e
def test_report_shows_prompt_escaped_timings_metrics_curves_and_files(full_scene: Path):
    text = (full_scene / "report.html").read_text()
    page = assert_self_contained(text, full_scene)
    assert html.escape(PROMPT, quote=True) in text and PROMPT not in text
    assert "<script>" not in text and "<b>lanterns" not in text
    steps = section(text, "steps")
    for s in STEPS:
        assert re.search(rf"<td>{s.name}</td><td><span class=\"badge ok\">complete</span></td><td class=\"num\">"
                         r"[0-9.]+ m?s</td>", steps), s.name  # fmt: skip
    metrics = section(text, "metrics")
    for group in ("Camera path vs ground truth", "Depth priors vs ground truth", "Normal priors", "Gaussian splats"):
        assert group in metrics
    psnr = SceneStore.open(full_scene).meta("splats").metrics.test_psnr
    assert f"{psnr:.4g}" in metrics and f"{psnr:.2f} dB" in section(text, "summary")
    assert "<img" in section(text, "curves")
    files = section(text, "files")
    assert 'href="splats.ply"' in files and 'href="scene.zarr/"' in files
    assert len(page.attrs_of("img")) >= 4 * 2 + 3 + 4  # attempts, previews, overview/paths/trajectory/curves


@pytest.mark.e2e
def test_scene_section_shows_the_videos_and_the_mesh(full_scene: Path):
    text = (full_scene / "report.html").read_text()
    assert text.index('<section id="scene">') < text.index('<section id="plan">')  # near the top
    scene = section(text, "scene")
    page = Page(scene)
    store = SceneStore.open(full_scene)
    out = store.root.attrs["config"]["steps"]["outputs"]
    w, h = store.meta("outputs").render_size
    videos = page.attrs_of("video")
    assert [v["src"] for v in videos] == list(VIDEOS)
    for v in videos:
        assert all(k in v for k in ("controls", "muted", "loop", "playsinline")) and v["preload"] == "metadata"
        assert (v["width"], v["height"]) == (str(w + w % 2), str(h + h % 2))  # the mp4 is padded to even sizes
    # stills: a sheet of 4 evenly spaced frames per video (count from the config), then the two mesh pictures
    n = out["video_frames"]
    for name in VIDEOS:
        assert f"{name}: 4 of its {n} frames, evenly spaced" in scene
        assert f"{n} frames, {n / out['video_fps']:.1f} s" in scene
    imgs = page.attrs_of("img")
    assert len(imgs) == 4
    front, over = (png_pixels(a) for a in imgs[2:])
    assert front.shape == over.shape == (320, 480, 3)  # ReportParams.mesh_view_width_px, the frames' aspect
    # the mesh was fused from the first camera's renders: seen from there it fills much of the picture
    assert (front != 255).any(axis=2).mean() > 0.25
    assert (over != 255).any(axis=2).mean() > 0.02
    red = (over[..., 0] > 180) & (over[..., 1] < 80) & (over[..., 2] < 80)
    assert red.sum() >= 30  # the camera path drawn over the overview
    assert "from the first camera of the video" in scene and "above and behind the camera path" in scene
    assert "No renders" not in scene and "No mesh" not in scene


@pytest.mark.e2e
def test_report_is_rewritten_only_when_the_store_changed(full_scene: Path, tmp_path: Path):
    scene = tmp_path / "copy"
    shutil.copytree(full_scene, scene)
    report = scene / "report.html"
    stamp = report.stat().st_mtime_ns
    # the copy's report names the original folder: it is stale here
    write_report(scene, only_if_stale=True)
    assert report.stat().st_mtime_ns != stamp and str(scene) in report.read_text()
    state = report_state(SceneStore.open(scene))
    assert f'<meta name="wonderverse-state" content="{state}">' in report.read_text()[:2000]
    before, stamp = report.read_bytes(), report.stat().st_mtime_ns
    t0 = time.perf_counter()
    assert write_report(scene, only_if_stale=True) == report
    seconds = time.perf_counter() - t0
    assert report.stat().st_mtime_ns == stamp and report.read_bytes() == before
    assert seconds < 0.5, f"an up-to-date report took {seconds:.2f} s to check"
    # a step group's cache key changes (as a re-run with other settings would): the report is redrawn
    SceneStore.open(scene, mode="r+").group("outputs").attrs["cache_key"] = "0" * 64
    write_report(scene, only_if_stale=True)
    assert report.stat().st_mtime_ns != stamp and report.read_bytes() != before
    assert f'content="{state}"' not in report.read_text()[:2000]
    # a video beside the store disappears: redrawn, and the page says so instead of linking it
    (scene / "novel.mp4").unlink()
    stamp = report.stat().st_mtime_ns
    text = write_report(scene, only_if_stale=True).read_text()
    assert report.stat().st_mtime_ns != stamp
    assert "No renders of the splats yet: novel.mp4 is written by the outputs step." in section(text, "scene")
    assert [v["src"] for v in Page(section(text, "scene")).attrs_of("video")] == ["flythrough.mp4"]


@pytest.mark.e2e
def test_per_segment_drawings_are_kept_between_reports_and_redrawn_when_their_segment_changes(
    full_scene: Path, tmp_path: Path
):
    """A growing world's report redraws only what changed (flows.report_cache); the page is the same either way."""
    scene = tmp_path / "copy"
    shutil.copytree(full_scene, scene)
    cache = scene / CACHE_DIR
    shutil.rmtree(cache)

    def page() -> str:
        return re.sub(r"written [^<]* UTC by", "", write_report(scene).read_text())

    def entries() -> dict[str, int]:
        return {p.name: p.stat().st_mtime_ns for p in cache.iterdir()}

    drawn = page()
    first = entries()
    assert {n.rsplit(".", 1)[1] for n in first} == {"png", "json"}  # plots, and the normal priors' errors
    (cache / "0123.png").write_bytes(b"left by an older report")
    assert page() == drawn
    assert entries() == first  # every entry read again as it was, the unused one removed
    figures = next(p for p in cache.iterdir() if p.suffix == ".json")
    good = figures.read_bytes()
    figures.write_text('{"mean_deg": "<script>", "n": [1]}')  # altered by hand: computed again, not trusted
    assert page() == drawn and figures.read_bytes() == good
    first = entries()
    # the rejected first attempt of s000 is checked again (its check's attributes change): its check plot and
    # top view are drawn again, nothing else
    store = SceneStore.open(scene, mode="r+")
    check = store.group("segments/s000/attempts/0/check")
    check.attrs["notes"] = [*check.attrs.get("notes", []), "checked again"]
    page()
    now = entries()
    assert len(set(first) - set(now)) == 2 and len(set(now) - set(first)) == 2
    assert all(now[n] == first[n] for n in set(first) & set(now))


@pytest.mark.e2e
def test_partial_scene_report_says_what_is_missing(partial_scene: Path, tmp_path: Path):
    scene = tmp_path / "scene"
    shutil.copytree(partial_scene, scene)
    store = SceneStore.open(scene, mode="r+")
    store.group("plan").attrs.pop("seconds")  # as written by an older WonderVerse
    # another step's exports, listed in `outputs` (one outside the scene must not be linked)
    (scene / "exports" / "colmap").mkdir(parents=True)
    (scene / "exports" / "colmap" / "cameras.txt").write_text("# camera\n")
    (scene / "mesh.glb").write_bytes(b"glTF" + bytes(96))
    (tmp_path / "secret.txt").write_text("no")
    files = [
        {"path": "mesh.glb", "bytes": 100},
        {"path": "exports/colmap", "bytes": 9, "description": "COLMAP model"},
        {"path": "../secret.txt", "bytes": 2},
        {"path": "absent.ply", "bytes": 0},
    ]
    frame = {"world_from_sfm": Sim3.identity().to_dict(), "up_in_sfm": [0.0, 0.0, 1.0], "world": "the sfm/ frame"}
    mesh = {"triangles": 0, "vertices": 0}
    with store.staged("outputs", "k", files=files, frame=frame, mesh=mesh, render_size=[96, 64]):
        pass
    text = write_report(scene).read_text()
    assert_self_contained(text, scene)
    assert "not checked" in row(text, "s000-a0") and "not checked yet</span></h3>" in text
    assert "The splats step has not run yet." in text
    scene_html = section(text, "scene")
    assert "No renders of the splats yet: novel.mp4 and flythrough.mp4 are written by the outputs step." in scene_html
    assert "No mesh yet: mesh.ply is written by the outputs step." in scene_html and "<video" not in scene_html
    steps = section(text, "steps")
    for name in ("check", "poses", "priors", "splats"):
        assert f'<td>{name}</td><td><span class="badge muted">not run</span>' in steps  # state `missing`
    assert '<td>plan</td><td><span class="badge ok">complete</span></td><td class="num">–</td>' in steps
    assert "not recorded" in steps
    files_html = section(text, "files")
    assert 'href="mesh.glb"' in files_html and "100 B" in files_html
    assert 'href="exports/colmap/"' in files_html and "COLMAP model" in files_html
    assert "secret" not in files_html and "absent.ply" not in files_html


def test_report_of_an_empty_store_and_of_no_store(tmp_path: Path):
    SceneStore.open_or_create(tmp_path / "empty")
    text = write_report(tmp_path / "empty").read_text()
    assert "Nothing has completed yet" in text and "The plan step has not run yet." in text
    (tmp_path / "none").mkdir()
    with pytest.raises(WonderError, match="holds no scene store"):
        write_report(tmp_path / "none")
    assert not (tmp_path / "none" / "report.html").exists()


# -- in a browser -------------------------------------------------------------------------------


@pytest.mark.e2e
def test_report_renders_in_headless_chromium(full_scene: Path):
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        if os.environ.get("WONDERVERSE_ALLOW_NO_BROWSER") == "1":
            pytest.skip("playwright is not installed")
        pytest.fail("the playwright package is missing: pip install playwright")
    report = full_scene / "report.html"
    errors: list[str] = []
    requests: list[str] = []
    with sync_playwright() as pw:
        browser = launch_browser(pw)
        try:
            page = browser.new_page(viewport=VIEWPORT)
            page.on("console", lambda m: errors.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(f"page error: {e}"))
            page.on("request", lambda r: requests.append(r.url))
            page.goto(report.as_uri(), wait_until="load")
            page.wait_for_function(
                "Array.from(document.querySelectorAll('video')).every(v => v.readyState >= 1 || v.error)",
                timeout=15_000,
            )
            videos = page.evaluate(
                "Array.from(document.querySelectorAll('video')).map(v => ({src: v.getAttribute('src'), "
                "ready: v.readyState, duration: v.duration, width: v.videoWidth, height: v.videoHeight, "
                "error: v.error && (v.error.code + ' ' + v.error.message)}))"
            )
            # metadata is not a picture: seek to the middle and wait until that frame is decoded
            decoded = page.evaluate(SEEK_AND_DECODE)
            images = page.evaluate(
                "Array.from(document.images).map(i => [i.complete, i.naturalWidth, i.naturalHeight, i.alt])"
            )
            overflow = page.evaluate("document.documentElement.scrollWidth - window.innerWidth")
            title = page.title()
            png = page.screenshot(full_page=True)
        finally:
            browser.close()
    assert errors == []
    # data URIs only, but for the videos beside the report: nothing else is fetched
    assert requests[0] == report.as_uri()
    assert set(requests[1:]) <= {(full_scene / v).as_uri() for v in VIDEOS}
    store = SceneStore.open(full_scene)
    out = store.root.attrs["config"]["steps"]["outputs"]
    w, h = store.meta("outputs").render_size
    assert [v["src"] for v in videos] == list(VIDEOS)
    for v in videos:
        assert v["error"] is None, v
        assert v["ready"] >= 1 and v["width"] == w + w % 2 and v["height"] == h + h % 2, v
        assert abs(v["duration"] - out["video_frames"] / out["video_fps"]) < 0.1, v
    assert decoded == [True, True], "a video's frame did not decode after seeking"
    assert len(images) >= 15
    assert all(ok and w > 0 and h > 0 for ok, w, h, _ in images), [alt for ok, w, h, alt in images if not w]
    assert overflow <= 0  # nothing wider than the window
    assert title == f"WonderVerse report — {full_scene.name}"
    shot = Image.open(io.BytesIO(png))
    assert shot.width == VIEWPORT["width"]
    assert shot.height > 5000  # a long page: 4 attempts' plots, 3 previews, curves, metrics
    # it is not blank: the header band is dark, the page body light
    px = np.asarray(shot.convert("RGB"))
    assert px[5, 5].mean() < 80 and px[-5, 5].mean() > 200


def test_the_report_says_what_the_export_pruned_and_shortened() -> None:
    from flows.report import _export_facts
    from wonderverse.schema.attrs import OutputFrame, PruneRecord

    pruned = PruneRecord(before=100, after=90, removed={"transparent": 7, "too_large": 3}, needles_shortened=4)
    facts = _export_facts(pruned, OutputFrame(world_from_sfm={}, up_in_sfm=[0, 0, 1], world="z up"))
    assert facts["Gaussians exported"] == "90 of 100" and facts["needles shortened"] == "4"
    assert facts["removed"] == "7 transparent, 3 too large"
