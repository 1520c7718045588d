"""The `wonderverse` command line.

Every user-facing problem (bad prompt, config, store, failed step) is one line on stderr and exit
code 2; nothing already in the store is touched before the inputs are validated.
"""

from __future__ import annotations

import errno
import glob
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console

from flows.engine import check_engine
from flows.serve import batch_command, serve_command
from flows.view import view_command
from wonderverse.errors import WonderError
from wonderverse.text import error_line

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="WonderVerse: text prompt -> extendable 3D scene.",
    pretty_exceptions_enable=False,
)
# Piped output is not cut to 80 columns: tables stay one row per line in logs and CI, and lines are not wrapped.
console = Console(stderr=True, width=None if sys.stderr.isatty() else 140, soft_wrap=not sys.stderr.isatty())
out = Console(width=None if sys.stdout.isatty() else 140, soft_wrap=not sys.stdout.isatty())


MAX_FOLDER_TRIES = 1000


def _default_out(prompt: str) -> Path:
    slug = "".join(c if c.isalnum() else "-" for c in prompt.lower()).strip("-")
    return Path("scenes") / ("-".join(filter(None, slug.split("-")))[:48] or "scene")


def _default_scene_folder(prompt: str, name_from: str | None = None) -> tuple[Path, str]:
    """(folder, note) for a run without --out: `scenes/<slug of name_from (default: prompt)>` unless that folder
    holds something else than a scene of `prompt` (another prompt's scene, other files), then the first free
    `<slug>-2`, `<slug>-3`, ...; `note` says why the name changed ("" when it did not). Many prompts share a slug
    ("a house, decorated!" and "A HOUSE -- decorated"), and a default folder must never replace another scene."""
    base = _default_out(name_from if name_from is not None else prompt)
    wanted = " ".join(prompt.split())  # as SceneSpec stores it
    for n in range(1, MAX_FOLDER_TRIES + 1):
        folder = base if n == 1 else base.with_name(f"{base.name}-{n}")
        if _fits_prompt(folder, wanted):
            return folder, "" if n == 1 else f"{base} holds another scene"
    raise WonderError(f"{base} and {MAX_FOLDER_TRIES - 1} numbered folders beside it are taken; choose one with --out")


def _fits_prompt(folder: Path, prompt: str) -> bool:
    """True when a run of `prompt` may use `folder`: absent, empty, or holding a scene made from `prompt` (read from
    the root's metadata without zarr: this is judged before anything heavy loads)."""
    from wonderverse.folders import LOCK_NAME, STORE_NAME, root_attrs

    if not folder.exists():
        return True
    if not folder.is_dir():
        return False
    if not (folder / STORE_NAME).exists():
        return not any(p.name != LOCK_NAME for p in folder.iterdir())
    spec = (root_attrs(folder) or {}).get("spec")
    return isinstance(spec, dict) and spec.get("prompt") == prompt


Engine = Annotated[
    str, typer.Option(help="auto (default: prefect when a Prefect server is configured, else local), prefect, local")
]
Preset = Annotated[
    str | None, typer.Option(help="preview | standard | high (default: the scene's, else what fits this machine)")
]
ReplaceSegments = Annotated[
    bool,
    typer.Option(
        "--replace-segments", help="allow this run to regenerate the scene's existing segments (other prompt or video)"
    ),
]
Strict = Annotated[
    bool,
    typer.Option(
        "--strict", help="exit 2 (an error line) when the final camera poses fail the quality gates (else a warning)"
    ),
]


def _choose_preset(preset: str | None, config: Path | None, stored: Any) -> tuple[str, str]:
    """(preset, why): the one named, else the config file's, else the scene's own, else this machine's default.
    A name given (even '') is checked when the config is built: a preset is a name, never a path."""
    from wonderverse.config import default_preset, read_yaml

    if preset is not None:
        return preset, "--preset"
    named = read_yaml(config).get("preset") if config else None
    if named is not None:
        return named, f"from {config}"
    if stored is not None:
        return stored.preset, "the scene's"
    return default_preset()


@app.command()
def generate(
    prompt: Annotated[str | None, typer.Argument(help="what the scene shows (or scene.prompt in --config)")] = None,
    preset: Preset = None,
    config: Annotated[Path | None, typer.Option(help="scene spec YAML (see configs/scenes/)")] = None,
    out_dir: Annotated[Path | None, typer.Option("--out", help="scene folder (default scenes/<prompt>)")] = None,
    until: Annotated[str | None, typer.Option(help="run only the steps this step needs")] = None,
    engine: Engine = "auto",
    seed: Annotated[int | None, typer.Option(help="scene seed (overrides the config)")] = None,
    dask: Annotated[
        str | None, typer.Option(help="existing Dask scheduler for per-segment work (tcp://host:8786)")
    ] = None,
    replace_segments: ReplaceSegments = False,
    strict: Strict = False,
) -> None:
    """Plan, render and reconstruct a scene; cached steps are skipped, the scene's extensions are kept."""
    from wonderverse.folders import check_scene_dir
    from wonderverse.yaml_files import read_yaml

    # judged cheapest first, before the steps, zarr or any engine load: a refusal costs what Python's start does
    _judge_engine(engine)
    if prompt is not None:
        _judge_prompt(prompt)
    file_scene = read_yaml(config).get("scene") if config else None
    file_prompt = file_scene.get("prompt") if isinstance(file_scene, dict) else None
    scene_dir, folder_note = (
        (out_dir, "") if out_dir else _default_scene_folder(str(prompt if prompt is not None else file_prompt or ""))
    )
    check_scene_dir(scene_dir)  # a bad --out is refused before anything slow
    from wonderverse.config import build_config, scene_config

    stored = scene_config(scene_dir)
    name, why = _choose_preset(preset, config, stored)
    overrides: dict = {"scene": {"seed": seed}} if seed is not None else {}
    if dask is not None:  # where work runs is not part of any cache key
        overrides["execution"] = {"dask_address": dask}
    cfg = build_config(prompt=prompt, preset=name, config_file=config, overrides=overrides or None)
    from flows.extend import with_extensions
    from flows.pipeline import claimed, needed_steps, run_pipeline

    steps = needed_steps(until)
    made = scene_config(scene_dir, "segments_config") or stored
    if made is not None and not replace_segments and not cfg.scene.extensions.added:
        cfg = with_extensions(cfg, made.scene.extensions.added)  # extensions are part of the scene
    read: list[str] = []
    if cfg.scene.video.backend == "files":
        from wonderverse.video import make_video_model

        # reads every clip: a bad one is refused before the store is touched; what reading did is said
        read = clip_notes(make_video_model(cfg.scene.video_source))
    with claimed(scene_dir, cfg, replace_segments):  # a busy, newer or read-only scene is refused in one line
        _run_with_progress(
            scene_dir,
            engine,
            f"preset {name} ({why})",
            lambda eng: run_pipeline(scene_dir, cfg, until, engine=eng, lock_held=True),
            len(steps),
            folder_note,
            config_notes(cfg) + read,
            strict=strict,
        )


def _judge_prompt(prompt: str) -> None:
    """The prompt's refusals (`wonderverse.text.words_problem`), worded as the config's, judged before the config
    (pydantic, numpy) loads."""
    from wonderverse.errors import ConfigError, shown
    from wonderverse.text import MAX_PROMPT_CHARS, words_problem

    problem = words_problem(prompt, "the prompt", MAX_PROMPT_CHARS)
    if problem is not None:
        raise ConfigError(f"invalid config: scene.prompt: {problem} (got {shown(prompt)})", field="scene.prompt")


def _run_with_progress(
    scene_dir: Path,
    engine: str,
    preset_note: str,
    run: Callable[[str], list[Any]],
    n_steps: int | None = None,
    folder_note: str = "",
    notes: list[str] | None = None,
    strict: bool = False,
) -> None:
    """The first line (preset, engine, scene, and `folder_note`: why the scene folder is not the default one) and
    `notes` (a line each), `run(engine)` with the progress display (`n_steps` steps, all by default) and the
    closing table, then the derived files and the list of what the run wrote; last, when this run's final poses
    fail the quality gates, a `warning:` line naming the figures (with `strict`: a WonderError, exit 2)."""
    from flows import progress
    from flows.engine import quiet_prefect, resolve_engine
    from tasks import STEPS

    eng = resolve_engine(engine)
    where = f"{scene_dir} ({folder_note})" if folder_note else str(scene_dir)
    console.print(f"wonderverse: {preset_note}, engine {eng}, scene {where}", highlight=False)
    for note in notes or []:
        console.print(f"wonderverse: {note}", highlight=False)
    if eng == "prefect":
        quiet_prefect()
    from flows.pipeline import StepFailed

    token = progress.current.set(progress.make_reporter(console, n_steps or len(STEPS)))
    try:
        results = run(eng)
    except StepFailed:
        _report_failure(scene_dir)  # the run stopped: the report says where and why, then the `error:` line
        raise
    finally:
        progress.current.reset(token)
    console.print(progress.results_table(results))
    _finish(scene_dir, results)
    _judge_poses(scene_dir, results, strict)


def _judge_poses(scene_dir: Path, results: list[Any], strict: bool) -> None:
    """The closing line when the poses this run ran or found current fail the quality gates
    (`flows.scene_quality`): one `warning:` line on stderr, or with `strict` one `error:` line and exit 2."""
    from flows.inspect import run_config
    from flows.scene_quality import gate_line, gates_of, pose_quality
    from wonderverse.store import SceneStore

    if "poses" not in {r.step for r in results}:
        return
    store = SceneStore.open(scene_dir)
    line = gate_line(pose_quality(store, gates_of(run_config(store))))
    if line is None:
        return
    if strict:
        raise WonderError(f"{line} (--strict)")
    print(f"warning: {error_line(line)}", file=sys.stderr)


def _report_failure(scene_dir: Path) -> None:
    """Write report.html for a run that stopped on a failed step (the store records where and why) and say where it
    is; a report that cannot be written is a warning, never a second error."""
    from flows.report import write_report

    try:
        report = write_report(scene_dir)
    except Exception as e:  # the step's failure is the error to report
        console.print(f"warning: no report.html for the failed run: {error_line(str(e))}", highlight=False)
        return
    out.print(f"report: {report}", highlight=False)


def _finish(scene_dir: Path, results: list[Any]) -> None:
    """Bring the files derived from the store up to date (the report; preview.mp4, contact_sheet.png and
    plots/ when `preview` made them) and say where everything is: the outputs only when this run's
    outputs step ran or found them current."""
    from flows.preview import PREVIEW_FILE, write_preview
    from flows.report import write_report

    changed = any(r.status == "ran" for r in results)
    report = write_report(scene_dir, only_if_stale=not changed)
    if changed and (Path(scene_dir) / PREVIEW_FILE).exists():
        write_preview(scene_dir)
    out.print(f"scene: {scene_dir}", highlight=False)
    for f in _output_files(scene_dir, {r.step for r in results}):
        out.print(f"  {f}", highlight=False)
    out.print(f"report: {report}", highlight=False)


def _output_files(scene_dir: Path, steps: set[str]) -> list[Path]:
    """The files the outputs step of this run wrote or found current (none when the run stopped before it)."""
    from wonderverse.schema import OUTPUTS
    from wonderverse.store import SceneStore

    if "outputs" not in steps:
        return []
    meta = SceneStore.open(scene_dir).meta(OUTPUTS.path)
    return [Path(scene_dir) / f.path for f in meta.files] if meta is not None else []


@app.command()
def reconstruct(
    clips: Annotated[list[str], typer.Argument(help="video files, image folders or globs; one segment each, in order")],
    out_dir: Annotated[Path | None, typer.Option("--out", help="scene folder (default scenes/<first clip>)")] = None,
    preset: Preset = None,
    config: Annotated[Path | None, typer.Option(help="settings YAML (steps, execution), as generate takes")] = None,
    depth_model: Annotated[
        Path | None, typer.Option(help="a local Depth Anything V2 folder (transformers format) for depth priors")
    ] = None,
    on_failure: Annotated[
        str, typer.Option(help="a clip that fails its check: keep_best (keep it, warned), drop, or fail")
    ] = "keep_best",
    fov_deg: Annotated[
        float | None, typer.Option(help="horizontal field of view when known (else estimated); held in every output")
    ] = None,
    intrinsics: Annotated[
        str | None,
        typer.Option(
            metavar="FX,FY,CX,CY",
            help="the camera's K when known, in pixels of the clips' frames (instead of --fov-deg); held in outputs",
        ),
    ] = None,
    refine_intrinsics: Annotated[
        bool, typer.Option(help="refine the camera given (--fov-deg, --intrinsics) in the global solve, not hold it")
    ] = False,
    shutter: Annotated[
        float | None,
        typer.Option(help="motion-blurred clips: the share of a frame's interval the shutter was open (0.5: 180°)"),
    ] = None,
    until: Annotated[str | None, typer.Option(help="run only the steps this step needs")] = None,
    engine: Engine = "auto",
    replace_segments: ReplaceSegments = False,
    strict: Strict = False,
) -> None:
    """Reconstruct your own clips (any video generator or a phone): check, poses, priors, splats, outputs."""
    from wonderverse.folders import check_scene_dir
    from wonderverse.text import control_character
    from wonderverse.video.files import group_sources

    _judge_engine(engine)
    paths = []
    for source in group_sources(clips):  # a shell turns frames/*.png into many arguments: one clip again
        if isinstance(source, list | tuple):
            folders = {Path(f).resolve().parent for f in source}
            if len(folders) != 1:
                raise WonderError("images from several folders: give each folder as one clip")
            source = folders.pop()
        paths.append(_clip_path(source))
    if depth_model is not None and not depth_model.is_dir():
        raise WonderError(f"--depth-model {depth_model}: no such folder (a local Depth Anything V2 folder)")
    options: dict[str, Any] = {} if fov_deg is None else {"fov_deg": fov_deg}
    if intrinsics is not None:
        options["intrinsics"] = _four_numbers(intrinsics)
    overrides: dict[str, Any] = {
        "scene": {"video": {"backend": "files", "clips": paths, "options": options}, "extensions": {"rounds": 0}},
        "steps": {"check": {"on_failure": on_failure}},
    }
    if refine_intrinsics:
        overrides["steps"]["poses"] = {"refine_intrinsics": True}
    if shutter is not None:  # the splats then smear their renders like the camera did (motion_blur_shutter)
        overrides["steps"]["splats"] = {"train": {"motion_blur_shutter": shutter}}
    if depth_model is not None:
        models = {"depth_backend": "depth_anything", "depth_model": str(depth_model.resolve()), "allow_download": False}
        overrides["steps"]["priors"] = {"models": {**models, "normal_backend": "from_depth"}}
    names = ", ".join(Path(p).name for p in paths)
    # a file name may hold any byte but "/": its control characters are not the user's words, so not refused here
    prompt = "reconstruction of " + "".join("?" if control_character(c) else c for c in names)
    scene_dir, folder_note = (out_dir, "") if out_dir else _default_scene_folder(prompt, Path(paths[0]).stem)
    check_scene_dir(scene_dir)
    from wonderverse.config import build_config, scene_config

    name, why = _choose_preset(preset, config, scene_config(scene_dir))
    cfg = build_config(prompt=prompt, preset=name, config_file=config, overrides=overrides)
    from flows.pipeline import claimed, needed_steps, run_pipeline
    from wonderverse.video import make_video_model

    steps = needed_steps(until)
    model = make_video_model(cfg.scene.video_source)  # reads every clip: a bad one is refused before any write
    with claimed(scene_dir, cfg, replace_segments):
        _run_with_progress(
            scene_dir,
            engine,
            f"preset {name} ({why})",
            lambda eng: run_pipeline(scene_dir, cfg, until, engine=eng, flow_name="reconstruct", lock_held=True),
            len(steps),
            folder_note=folder_note,
            notes=config_notes(cfg) + clip_notes(model),
            strict=strict,
        )


def _four_numbers(text: str) -> list[float]:
    """`--intrinsics FX,FY,CX,CY` as four numbers; WonderError in one line otherwise (the config judges their
    values)."""
    parts = text.replace(" ", "").split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 4:
        raise WonderError(f"--intrinsics {text}: four numbers FX,FY,CX,CY (pixels of the clips' frames)")
    return values


def _clip_path(source: str) -> str:
    """The absolute path of a clip argument (a glob stays a pattern); WonderError naming it when it is missing, a
    symlink loop, or neither a file nor a folder (a device, a pipe)."""
    try:
        path = Path(source).resolve()
    except (RuntimeError, OSError) as e:  # Python 3.11 raises RuntimeError for a symlink loop
        raise WonderError(f"{source}: cannot be read ({' '.join(str(e).split())})") from None
    if not path.exists():
        if glob.glob(str(path)):
            return str(path)
        raise WonderError(f"{source}: no such file or folder")
    if not (path.is_file() or path.is_dir()):
        raise WonderError(f"{source}: not a video file or a folder of images (a device or a pipe)")
    return str(path)


def clip_notes(model: Any) -> list[str]:
    """What reading each clip did to it (`Clip.notes`: frames subsampled or left out, resizing, the frame rate or
    field of view assumed), a line per clip: `clip NAME: note; note`."""
    lines = []
    for c in getattr(model, "clips", []):
        if c.notes:
            name = c.name + ("/" if Path(c.source).is_dir() else "")
            lines.append(f"clip {name}: {'; '.join(c.notes)}")
    return lines


def config_notes(cfg: Any) -> list[str]:
    """What a user must know about this run's configuration before it starts, one line each."""
    notes = []
    if not cfg.steps.priors.models.any:
        notes.append(
            "priors: none (no depth model named): the splats train on colours alone; --depth-model PATH (a local "
            "Depth Anything V2 folder) or steps.priors.models in --config adds depth and normal priors"
        )
    return notes


@app.command()
def extend(
    scene_dir: Annotated[Path, typer.Argument(help="scene folder made by `generate`")],
    words: Annotated[str, typer.Argument(help="where to extend, e.g. 'a frozen lake beyond the trees on the left'")],
    engine: Engine = "auto",
) -> None:
    """Extend a scene in words: plan, generate, check one more segment; update poses, priors, splats, outputs."""
    from flows.extend import extension_config

    _judge_engine(engine)
    cfg = extension_config(scene_dir, words)  # no scene, no completed run, clips, unusable words: refused here
    from flows.pipeline import claimed, run_pipeline

    with claimed(scene_dir, cfg):
        _run_with_progress(
            scene_dir,
            engine,
            f"preset {cfg.preset} (the scene's)",
            lambda eng: run_pipeline(scene_dir, cfg, engine=eng, flow_name="extend", lock_held=True),
        )


@app.command()
def inspect(
    scene_dir: Annotated[Path, typer.Argument(help="scene folder")],
    as_json: Annotated[bool, typer.Option("--json", help="machine-readable output (schema in docs/usage.md)")] = False,
) -> None:
    """Steps with status and cache key, segments (or clips) with attempts and checks, priors, arrays and sizes."""
    from rich.table import Table

    from flows.inspect import damaged_lines, guide_words, scene_spec, scene_summary
    from wonderverse.report import CLIP_VERDICTS, STEP_STATE_WORDS
    from wonderverse.store import SceneStore

    store = SceneStore.open(scene_dir)
    info = scene_summary(store)
    if as_json:
        print(json.dumps(info.model_dump(mode="json"), indent=2))
        return
    clips = {c.segment: c for c in info.clips or []}
    if info.clips is not None:
        n = len(info.clips)
        out.print(f"[bold]{info.scene_dir}[/] — reconstruction of {n} clip{'s' * (n != 1)}", highlight=False)
    else:
        spec = scene_spec(store)
        prompt, seed = (spec.prompt, spec.seed) if spec is not None else ("?", None)
        out.print(f"[bold]{info.scene_dir}[/] — {prompt!r} (seed {seed})")
    later = "" if info.priors.computed else " (the priors step has not run)"
    out.print(f"priors: {info.priors.words}{later}", highlight=False)
    t = Table(title="steps")
    for c in ("step", "status", "cache key"):
        t.add_column(c)
    for s in info.steps:
        t.add_row(s.name, STEP_STATE_WORDS.get(s.status, s.status), (s.cache_key or "-")[:12])
    out.print(t)
    failed = failed_run_line(store)
    if failed:
        out.print(failed, highlight=False)
    if clips:
        t = Table(title="clips (in the order given; each is one segment)")
        columns: tuple[str, ...] = ("segment", "clip", "frames", "K", "check", "MB")
    else:
        t = Table(title="segments (stitched order: " + " ".join(info.order) + ")")
        columns = ("segment", "role", "move", "attempts", "accepted", "check", "frames", "MB")
    # guided extensions: the share of known pixels of the guide the shown attempt (accepted, else the last) came from
    guided = not clips and any(a.guide is not None for s in info.segments for a in s.attempts)
    unguided: list[str] = []
    if guided:
        columns = (*columns[:6], "guide known", *columns[6:])
    for c in columns:
        t.add_column(c)
    for s in info.segments:
        acc = next((a for a in s.attempts if a.index == s.accepted_attempt), None)
        shown = acc or (s.attempts[-1] if s.attempts else None)
        check = acc.check if acc is not None else None
        verdict = "-" if check is None else ("ok" if check.accepted else "rejected")
        frames_info = acc.arrays.get("frames") if acc is not None else None
        mb = sum(a.bytes for a in s.attempts) / 1e6
        clip = clips.get(s.id)
        if clip is not None:
            fov = f" {clip.fov_deg:.1f}°" if clip.fov_deg is not None else ""
            size = f" ({clip.size[0]}x{clip.size[1]})" if clip.size else ""
            frames = "-" if clip.frames is None else f"{clip.frames}{size}"
            row = [s.id, _clip_label(clip.name, clip.kind), frames, f"{clip.k_source or '-'}{fov}"]
            t.add_row(*row, CLIP_VERDICTS[clip.verdict], f"{mb:.1f}")
            continue
        row = [s.id, s.role, s.move, str(len(s.attempts)), str(s.accepted_attempt), verdict]
        g = shown.guide if shown is not None else None
        if guided:
            row.append(guide_words(g))
            if g is not None and guide_words(g) == "none":
                unguided.append(f"{s.id}: generated without a guide: {g.reason or 'no reason recorded'}")
        t.add_row(*row, "x".join(map(str, frames_info.shape)) if frames_info else "-", f"{mb:.1f}")
    out.print(t)
    for line in unguided:
        out.print(line, highlight=False)
    for c in clips.values():
        if c.verdict == "recovered" and c.check_registered and c.poses_registered:
            (a, n), (b, m) = c.check_registered, c.poses_registered
            out.print(
                f"{c.segment} {_clip_label(c.name, c.kind)}: recovered: its check registered {a} of {n} frames, "
                f"the global solve {b} of {m}",
                highlight=False,
            )
        if c.reasons:
            out.print(f"{c.segment} {_clip_label(c.name, c.kind)}: {'; '.join(c.reasons)}", highlight=False)
    if info.global_k is not None:
        k = info.global_k
        fov = f", {k.fov_deg:.1f}° horizontal field of view" if k.fov_deg is not None else ""
        why = f" ({k.reason})" if k.reason else ""
        out.print(f"camera every output uses: K {k.k_source}{fov}{why}", highlight=False)
        if clips and k.held is False and any(c.fov_deg is not None for c in clips.values()):
            out.print("  (the clips' K column is their own check's; the outputs use this one)", highlight=False)
    for line in _quality_lines(info.quality):
        out.print(line, highlight=False)
    for e in info.extensions:
        out.print(f"extension {e.segment}: {e.words!r}", highlight=False)
    for line in damaged_lines(info):
        out.print(line, highlight=False)
    out.print(f"store size: {info.size_bytes / 1e6:.1f} MB")


def failed_run_line(store: Any) -> str:
    """'last run failed at step poses (2026-12-05T18:40:00+00:00): <why>; it completed plan, check', or "" when the
    scene's last run did not fail."""
    from flows.inspect import root_meta

    f = root_meta(store).failed_run
    if f is None:
        return ""
    done = f"; it completed {', '.join(f.completed)} first" if f.completed else "; it completed no step first"
    return f"last run failed at step {f.step} ({f.finished}): {f.error}{done}"


def _quality_lines(q: Any) -> list[str]:
    """The poses against their gates and the splats' PSNR/SSIM, a line each (`flows.scene_quality.Quality`)."""
    lines = []
    if q.poses is not None:
        p = q.poses
        gates = {True: "passes the quality gates", False: "FAILS the quality gates: " + "; ".join(p.problems)}
        ate = f", ATE {100 * p.ate_frac:.2f} % of the path" if p.ate_frac is not None else ", ATE not available"
        lines.append(
            f"poses: {p.registered} of {p.frames_used} views registered, {p.points} points{ate}; "
            + gates.get(p.passed, "taken from the conditioning path (no SfM to judge)")
        )
    if q.splats is not None:
        s = q.splats
        if s.psnr_label == "held-out":
            lines.append(f"splats: held-out PSNR {s.held_out_psnr_db:.2f} dB, SSIM {s.held_out_ssim or 0:.3f} "
                         f"({s.held_out_views} views held out)")  # fmt: skip
        elif s.training_psnr_db is not None:
            lines.append(f"splats: training PSNR {s.training_psnr_db:.2f} dB (no view held out)")
    return lines


def _clip_label(name: str, kind: str) -> str:
    """A clip's name as a person reads it: folders end with a slash."""
    return name + ("/" if kind == "folder" else "")


@app.command()
def preview(scene_dir: Annotated[Path, typer.Argument(help="scene folder")]) -> None:
    """Write preview.mp4 (the stitched video), contact_sheet.png and plots/ (check plots, top views)."""
    from flows.preview import write_preview
    from flows.report import REPORT_NAME, write_report

    files = write_preview(scene_dir)
    if (scene_dir / REPORT_NAME).exists():  # it lists these files: keep it current
        files.append(write_report(scene_dir, only_if_stale=True))
    for f in files:
        out.print(f"wrote {f}", highlight=False)


@app.command()
def report(scene_dir: Annotated[Path, typer.Argument(help="scene folder")]) -> None:
    """Write report.html: plan, attempts and check plots, priors, training curves, timings, metrics, files."""
    from flows.report import write_report

    out.print(f"wrote {write_report(scene_dir)}", highlight=False)


app.command("serve")(serve_command)
app.command("batch")(batch_command)
app.command("view")(view_command)


@app.command("studio")
def studio(
    root: Annotated[Path, typer.Argument(help="folder of scenes (made when absent)")] = Path("scenes"),
    port: Annotated[int, typer.Option(help="port (default: a free one)", min=0, max=65535)] = 0,
    host: Annotated[str, typer.Option(help="address to bind (default 127.0.0.1: this machine only)")] = "127.0.0.1",
    config: Annotated[Path | None, typer.Option(help="settings YAML for new scenes, as generate takes")] = None,
    engine: Engine = "auto",
) -> None:
    """Build and grow scenes in the browser: create from a prompt, watch progress, view in 3D, extend, download."""
    from flows.studio import serve_studio  # the web stack loads only here: `wonderverse --help` stays fast

    serve_studio(root, host, port, config, engine)


def _quiet_libraries() -> None:
    """Only the command's own lines reach the terminal: other libraries' Python warnings (a deprecation noticed at
    import, before a run's first line) and log records of loggers nobody configured (Python would print them through
    its last-resort handler) are dropped; our own warnings stay, and PYTHONWARNINGS / -W still decide when given."""
    import logging
    import warnings

    if not sys.warnoptions:  # ours keep Python's default filters
        warnings.filterwarnings("ignore", module=r"(?!(wonderverse|flows|tasks)(\.|$))")
    logging.getLogger().addHandler(logging.NullHandler())


# A file-size limit (`ulimit -f`) shows as EFBIG on the first large write, in our files or in Prefect's database
FSIZE_ADVICE = "a file-size limit is set for this shell (ulimit -f): raise it with `ulimit -f unlimited`"
MIN_FILE_SIZE_LIMIT = 1 << 30  # bytes: a scene's files and Prefect's database need more than this


def _judge_engine(engine: str) -> None:
    """The engine's refusals before anything is written: an unknown name; a file-size limit too small for a run
    (under Prefect it would surface as a database error after its server started)."""
    import resource

    check_engine(engine)
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft != resource.RLIM_INFINITY and soft < MIN_FILE_SIZE_LIMIT:
        raise WonderError(f"files may be at most {soft} bytes here: {FSIZE_ADVICE}")


def main() -> None:
    """`wonderverse ...`: run the command in a supervised child (Ctrl-C, SIGTERM: see flows.supervise); in the
    child, run it, user errors becoming one line on stderr and exit code 2."""
    from flows.supervise import CHILD_ENV, run_supervised, start_reaper

    if os.environ.get(CHILD_ENV) != "1":
        sys.exit(run_supervised(sys.argv[1:]))
    start_reaper()
    _quiet_libraries()
    try:
        app(standalone_mode=False)
    except WonderError as e:  # StepFailed included
        print(f"error: {error_line(str(e))}", file=sys.stderr)
        sys.exit(2)
    except OSError as e:  # the disk, not the code: full, read-only, gone while writing
        where = f"{e.filename}: " if e.filename else ""
        why = (e.strerror or str(e)) + (f" ({FSIZE_ADVICE})" if e.errno == errno.EFBIG else "")
        print(f"error: {error_line(where + why)}", file=sys.stderr)
        sys.exit(2)
    except (typer.Exit, SystemExit) as e:
        code = getattr(e, "exit_code", getattr(e, "code", 0))
        sys.exit(code)
    except typer.Abort:
        sys.exit(130)
    except Exception as e:
        # Usage errors (no such option, a missing argument): click's exceptions, vendored by typer >= 0.29
        if hasattr(e, "format_message") and hasattr(e, "exit_code"):
            print(f"error: {error_line(e.format_message())} (see --help)", file=sys.stderr)
            sys.exit(2)
        raise


if __name__ == "__main__":  # `python -m flows.cli ...`, as `wonderverse ...`
    main()
