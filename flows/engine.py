"""Which engine runs a pipeline, decided without importing Prefect.

`auto` (the default) runs the steps as plain in-process calls unless a Prefect server is configured
(PREFECT_API_URL in the environment or in the active Prefect profile): then it runs them as a Prefect flow
that the server's UI shows. Starting Prefect's ephemeral API costs 5-15 s on a 2-core machine and shows
nothing to anyone, so a local run does not pay for it; `--engine prefect` still asks for it explicitly.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Literal

from wonderverse.errors import WonderError

ENGINES = ("auto", "prefect", "local")
Engine = Literal["auto", "prefect", "local"]


def check_engine(engine: str) -> Engine:
    if engine not in ENGINES:
        raise WonderError(f"--engine must be {', '.join(ENGINES[:-1])} or {ENGINES[-1]} (got {engine!r})")
    return engine  # type: ignore[return-value]


def configured_api_url() -> str | None:
    """PREFECT_API_URL from the environment, else from the active profile of Prefect's profiles file."""
    url = os.environ.get("PREFECT_API_URL")
    if url is not None:
        return url or None
    home = Path(os.environ.get("PREFECT_HOME", "~/.prefect")).expanduser()
    path = Path(os.environ.get("PREFECT_PROFILES_PATH", home / "profiles.toml")).expanduser()
    try:
        profiles = tomllib.loads(path.read_text())
    except (OSError, ValueError):
        return None
    active = os.environ.get("PREFECT_PROFILE") or profiles.get("active") or "ephemeral"
    profile = profiles.get("profiles", {}).get(active, {})
    value = profile.get("PREFECT_API_URL") if isinstance(profile, dict) else None
    return value if isinstance(value, str) and value else None


def resolve_engine(engine: str) -> Literal["prefect", "local"]:
    """`prefect` or `local`: `auto` is Prefect exactly when a Prefect server is configured."""
    if check_engine(engine) == "auto":
        return "prefect" if configured_api_url() else "local"
    return engine  # type: ignore[return-value]


def quiet_prefect(console_level: str | None = "CRITICAL") -> None:
    """Keep Prefect's telemetry off the network and, at `console_level`, its own chatter out of the user's
    terminal: its logs still reach its API (the UI), the terminal shows only our lines, and a failure is
    one `error:` line. `serve` keeps Prefect's console logs (None): there they are the point."""
    if console_level is not None:
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL", console_level)
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_CLI_PROMPT", "false")
    # A fresh Prefect home migrates its database on the first start: on 2 cores that outlasts the 20 s default.
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")
