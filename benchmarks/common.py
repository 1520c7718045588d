"""Shared benchmark plumbing: argument parsing, machine description, the closing table + JSON line."""

from __future__ import annotations

import argparse
import json
import os
import platform
from typing import Any

from rich.console import Console
from rich.table import Table


def parse_args(description: str) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--quick", action="store_true", help="smaller workload (CI-sized)")
    return p.parse_args()


def machine() -> str:
    return f"{platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}"


def table(rows: list[dict[str, Any]], title: str) -> None:
    """Print `rows` (dicts with the same keys) as a table titled `title` and the machine."""
    t = Table(title=f"{title} — {machine()}")
    for col in rows[0] if rows else []:
        t.add_column(col)
    for r in rows:
        t.add_row(*(f"{v:.4g}" if isinstance(v, float) else str(v) for v in r.values()))
    Console(width=160).print(t)


def report(title: str, rows: list[dict[str, Any]], headline: dict[str, float | int]) -> None:
    """Print `rows` as a table, then the headline figures as the last line (JSON)."""
    table(rows, title)
    print(json.dumps(headline), flush=True)
