"""Many scenes, on a schedule: the `batch` flow and `wonderverse serve` / `wonderverse batch`.

`batch` runs the `generate` flow once per scene spec YAML in a folder, each as a subflow named after
the spec, so the Prefect UI shows every scene's steps as task runs; a scene that fails does not stop
the others. `serve` registers one cron deployment of `batch` with a Prefect server and runs it
(blocking); runs are executed here, one at a time. Local `batch` runs need no server (Prefect's
ephemeral API), exactly like `wonderverse generate`.

Prefect is imported inside functions only: the CLI imports this module at start-up.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from flows.engine import quiet_prefect
from wonderverse.errors import WonderError

SPEC_SUFFIXES = (".yaml", ".yml")
DEFAULT_CRON = "0 3 * * *"  # daily at 03:00 UTC
ENTRYPOINT = "flows.serve.batch"  # module path the runner imports; resolved by the module __getattr__ below


def find_specs(specs_dir: Path | str) -> list[Path]:
    """The scene spec files directly in `specs_dir` (*.yaml, *.yml), sorted by name. Each one's name (its stem) names
    its scene's folder, OUT/<stem>: a name that is no single folder name (`..yaml` and `...yaml` are `.` and `..`:
    OUT itself and its parent) is refused in one line, for the whole batch, before anything runs."""
    from wonderverse.folders import check_child_name

    d = Path(specs_dir)
    if not d.is_dir():
        raise WonderError(f"scene spec folder {d} does not exist or is not a folder")
    specs = sorted(p for p in d.iterdir() if p.suffix in SPEC_SUFFIXES and p.is_file())
    for p in specs:
        check_child_name(p.stem, f"scene spec {p.name}")
    return specs


def _one_line(e: BaseException) -> str:
    return " ".join(f"{type(e).__name__}: {e}".split())


def load_spec(spec_file: Path | str, dask_address: str | None = None) -> Any:
    """The RunConfig of one scene spec file; WonderError (ConfigError) when invalid."""
    from wonderverse.config import build_config

    overrides = None
    if dask_address:  # where work runs is not part of any cache key (as `generate --dask`)
        overrides = {"execution": {"dask_address": dask_address}}
    return build_config(config_file=Path(spec_file), overrides=overrides)


def _batch(specs_dir: str, out_root: str, until: str | None = None, dask_address: str | None = None) -> dict[str, Any]:
    """Run `generate` for every spec in `specs_dir` into `out_root/<spec stem>`, one after another.

    Returns {"scenes": [{spec, scene_dir, status: completed|failed, seconds, steps: {step: ran|cached|failed},
    error}], "completed": n, "failed": m}; as the data of a Failed state (message naming the failed
    scenes) when any scene failed, so the run shows as failed in the UI. Failures are caught per scene
    and logged; an invalid spec is logged without a subflow."""
    from prefect import get_run_logger
    from prefect.states import Failed

    from flows.pipeline import generate_flow

    logger = get_run_logger()
    scenes: list[dict[str, Any]] = []
    specs = find_specs(specs_dir)
    logger.info("%d scene spec(s) in %s", len(specs), specs_dir)
    for spec in specs:
        scene_dir = Path(out_root) / spec.stem
        entry: dict[str, Any] = {
            "spec": spec.stem,
            "scene_dir": str(scene_dir),
            "status": "failed",
            "steps": {},
            "error": None,
        }
        t0 = time.perf_counter()
        try:
            cfg = load_spec(spec, dask_address)
            results = generate_flow().with_options(flow_run_name=spec.stem)(str(scene_dir), cfg, until)
            entry.update(status="completed", steps={r.step: r.status for r in results}, error=None)
            logger.info("%s: completed (%s)", spec.stem, ", ".join(f"{r.step} {r.status}" for r in results))
        except Exception as e:  # one scene's failure must not stop the others
            entry["error"] = _one_line(e)
            results = getattr(e, "results", None)  # StepFailed carries what ran before the failure
            if results:
                entry["steps"] = {r.step: r.status for r in results}
            logger.error("%s: failed: %s", spec.stem, entry["error"])
        entry["seconds"] = round(time.perf_counter() - t0, 2)
        scenes.append(entry)
    failed = [s["spec"] for s in scenes if s["status"] == "failed"]
    summary = {"scenes": scenes, "completed": len(scenes) - len(failed), "failed": len(failed)}
    if failed:
        return Failed(message=f"{len(failed)} of {len(scenes)} scenes failed: {', '.join(failed)}", data=summary)
    return summary


_flows: dict[str, Any] = {}


def batch_flow() -> Any:
    """The Prefect flow `batch` (built on first use so importing this module stays light)."""
    if "batch" not in _flows:
        from prefect import flow

        _flows["batch"] = flow(name="batch", log_prints=False)(_batch)
    return _flows["batch"]


def __getattr__(name: str) -> Any:
    # The runner loads a served deployment's flow by importing ENTRYPOINT: `flows.serve.batch`.
    if name == "batch":
        return batch_flow()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_batch(
    specs_dir: Path | str, out_root: Path | str, until: str | None = None, dask_address: str | None = None
) -> dict[str, Any]:
    """Run the `batch` flow in this process (on PREFECT_API_URL if set, else Prefect's ephemeral API)."""
    if not find_specs(specs_dir):  # a missing folder, a bad spec name, no spec: user errors before Prefect starts
        raise WonderError(f"no scene specs (*.yaml, *.yml regular files) in {specs_dir}")
    _check_out_root(Path(out_root))
    _check_until(until)
    args = (str(Path(specs_dir).resolve()), str(Path(out_root).resolve()), until, dask_address)
    state = batch_flow()(*args, return_state=True)
    summary = state.result(raise_on_failure=False)
    if isinstance(summary, BaseException):  # the flow itself broke (not a scene): that is a bug, show it
        raise summary
    return summary


def _check_out_root(out_root: Path) -> None:
    """WonderError before Prefect starts when `out_root` (the folder of the scenes' folders) is a file, or lies under
    one, or cannot be created or written."""
    from wonderverse.store import check_writable

    existing = next(p for p in (out_root, *out_root.absolute().parents) if p.exists() or p == p.parent)
    if not existing.is_dir():
        raise WonderError(f"--out {out_root}: {existing} is not a folder (each scene goes to OUT/<spec file name>)")
    check_writable(existing, f"--out {out_root}")


def _check_until(until: str | None) -> None:
    from tasks import STEP_NAMES

    if until is not None and until not in STEP_NAMES:
        raise WonderError(f"unknown step {until!r}; steps are: {', '.join(STEP_NAMES)}")


def api_url() -> str:
    """The Prefect server's API URL (PREFECT_API_URL, from the environment or the active profile).

    Raises WonderError when unset, when no server answers there, or when it refuses our credentials
    (PREFECT_API_AUTH_STRING against a server started with PREFECT_SERVER_API_AUTH_STRING)."""
    import httpx
    from prefect.settings import get_current_settings

    api = get_current_settings().api
    url = (api.url or "").rstrip("/")
    if not url:
        raise WonderError(
            "serve needs a Prefect server: start one with `prefect server start` (it listens on "
            "127.0.0.1:4200) and set PREFECT_API_URL=http://127.0.0.1:4200/api"
        )
    secret = api.auth_string.get_secret_value() if api.auth_string else None
    auth = tuple(secret.split(":", 1)) if secret and ":" in secret else None
    try:
        # /admin/version needs the credentials when the server has some (/health never does)
        r = httpx.get(f"{url}/admin/version", timeout=10, auth=auth)
    except httpx.HTTPError as e:
        raise WonderError(
            f"no Prefect server answers at PREFECT_API_URL={url} ({_one_line(e)}); start it with `prefect server start`"
        ) from None
    if r.status_code in (401, 403):
        raise WonderError(
            f"the Prefect server at {url} refused our credentials: set PREFECT_API_AUTH_STRING=user:password "
            "(the server's PREFECT_SERVER_API_AUTH_STRING)"
        )
    if r.status_code != 200:
        raise WonderError(
            f"PREFECT_API_URL={url} does not look like a Prefect API (GET /admin/version: {r.status_code})"
        )
    return url


def build_deployment(
    specs_dir: Path | str,
    out_root: Path | str,
    cron: str = DEFAULT_CRON,
    until: str | None = None,
    dask_address: str | None = None,
    name: str | None = None,
) -> Any:
    """The cron deployment of `batch` over `specs_dir` (a prefect RunnerDeployment, not yet registered).

    Paths are made absolute: runs execute in subprocesses that may start elsewhere."""
    from prefect.client.schemas.schedules import CronSchedule
    from prefect.types.entrypoint import EntrypointType

    _check_until(until)
    specs_dir, out_root = Path(specs_dir).resolve(), Path(out_root).resolve()
    if not find_specs(specs_dir):
        raise WonderError(f"no scene specs (*.yaml) in {specs_dir}")
    try:
        CronSchedule(cron=cron)
    except ValueError:
        raise WonderError(f"--cron: not a valid cron expression: {cron!r} (e.g. '0 3 * * *')") from None
    deployment = batch_flow().to_deployment(
        name=name or specs_dir.name,
        cron=cron,
        parameters={
            "specs_dir": str(specs_dir),
            "out_root": str(out_root),
            "until": until,
            "dask_address": dask_address,
        },
        description=f"wonderverse: every scene spec in {specs_dir} into {out_root}/<spec name>",
        tags=["wonderverse"],
        entrypoint_type=EntrypointType.MODULE_PATH,
    )
    deployment.entrypoint = ENTRYPOINT
    return deployment


def serve(
    specs_dir: Path | str,
    out_root: Path | str,
    cron: str = DEFAULT_CRON,
    until: str | None = None,
    dask_address: str | None = None,
    name: str | None = None,
) -> None:
    """Register the `batch` deployment with the server at PREFECT_API_URL and run its runs here (blocks).

    One run at a time (`limit=1`): scenes never get two writers and the machine is not oversubscribed.
    Stopping (Ctrl-C) pauses the schedule."""
    from prefect import serve as prefect_serve

    api_url()
    deployment = build_deployment(specs_dir, out_root, cron, until, dask_address, name)
    prefect_serve(deployment, limit=1)


SpecsDir = Annotated[Path, typer.Argument(help="folder of scene spec YAML files (see configs/scenes/)")]
OutRoot = Annotated[Path, typer.Option("--out", help="each scene goes to OUT/<spec file name>")]
Until = Annotated[str | None, typer.Option(help="run only the steps this step needs")]
Dask = Annotated[str | None, typer.Option(help="existing Dask scheduler for per-segment work (tcp://host:8786)")]


def serve_command(
    specs_dir: SpecsDir = Path("configs/scenes"),
    out_root: OutRoot = Path("scenes"),
    cron: Annotated[str, typer.Option(help="cron schedule, UTC ('0 3 * * *': daily at 03:00)")] = DEFAULT_CRON,
    until: Until = None,
    dask: Dask = None,
    name: Annotated[str | None, typer.Option(help="deployment name (default: the folder's name)")] = None,
) -> None:
    """Serve a cron deployment that runs every scene spec in a folder (needs a Prefect server and PREFECT_API_URL)."""
    quiet_prefect(console_level=None)
    serve(specs_dir, out_root, cron, until, dask, name)


def batch_command(
    specs_dir: SpecsDir = Path("configs/scenes"),
    out_root: OutRoot = Path("scenes"),
    until: Until = None,
    dask: Dask = None,
) -> None:
    """Run every scene spec in a folder now, one after another; a failing scene does not stop the others."""
    from rich.console import Console
    from rich.table import Table

    # Quiet terminal (a failed scene is a row of the table below, not Prefect's traceback), but INFO logs still
    # reach the API: with PREFECT_API_URL set they show in the UI.
    quiet_prefect()
    summary = run_batch(specs_dir, out_root, until, dask)
    t = Table(title="batch")
    for c in ("scene", "status", "seconds", "steps / error"):
        t.add_column(c)
    for s in summary["scenes"]:
        steps = ", ".join(f"{k} {v}" for k, v in s["steps"].items())
        t.add_row(s["spec"], s["status"], f"{s['seconds']:.1f}", s["error"] or steps)
    Console(width=None if sys.stdout.isatty() else 140).print(t)
    if summary["failed"]:
        failed = ", ".join(s["spec"] for s in summary["scenes"] if s["status"] == "failed")
        raise WonderError(f"{summary['failed']} of {len(summary['scenes'])} scenes failed: {failed}")


app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False)
app.command("serve")(serve_command)
app.command("batch")(batch_command)


if __name__ == "__main__":  # `python -m flows.serve serve|batch ...` (same as `wonderverse serve|batch`)
    try:
        app(standalone_mode=False)
    except WonderError as e:
        print(f"error: {' '.join(str(e).split())}", file=sys.stderr)
        sys.exit(2)
