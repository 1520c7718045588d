"""The studio's jobs: each one a `wonderverse` command (generate, extend, reconstruct) in a child process, one per
scene at a time, its progress fanned out to every open event stream.

Why the CLI in a child: the scene lock, the validation and the one-line errors are then exactly the terminal's,
a job that crashes or is killed by the OS takes nothing of the studio with it, and the page stays live while a job
computes. The child is the supervised command (`flows.supervise`): the run itself goes in a session of its own,
which its supervisor, a process of the studio's own group, kills with everything it started when the supervisor is
killed (Ctrl-C of the studio kills the studio's group and every descendant). Its progress comes as JSON lines
(`flows.progress.JsonReporter`, asked for through PROGRESS_ENV); its `error: ...` line is the job's error.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import signal
import sys
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flows.progress import JSON_PREFIX, PROGRESS_ENV
from flows.supervise import CHILD_ENV

EVENTS_KEPT = 5000  # events a stream opened late (or reopened) can still replay, `since` an id
QUEUE_EVENTS = 2000  # events waiting for one slow stream before it is dropped (the page then reconnects)
LOG_LINES = 200  # last lines of a job's output kept for the page
LINE_LIMIT = 1 << 20  # bytes of one output line (a results table is one line per row, far below)


@dataclass
class Job:
    """One command run for a scene; `public()` is what the API shows."""

    id: str
    scene: str
    kind: str
    argv: list[str]
    state: str = "queued"  # queued | running | done | failed
    step: str | None = None
    progress: dict[str, Any] | None = None
    error: str | None = None
    returncode: int | None = None
    created: float = field(default_factory=time.time)
    ended: float | None = None
    log: deque[str] = field(default_factory=lambda: deque(maxlen=LOG_LINES))
    pid: int | None = None

    @property
    def active(self) -> bool:
        return self.state in ("queued", "running")

    def public(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "scene": self.scene,
            "kind": self.kind,
            "state": self.state,
            "step": self.step,
            "progress": self.progress,
            "error": self.error,
            "returncode": self.returncode,
            "created": self.created,
            "ended": self.ended,
            "log": list(self.log)[-20:],
        }


class Busy(Exception):
    """The scene already has a job queued or running (409 with its id)."""

    def __init__(self, job: Job):
        super().__init__(f"scene {job.scene!r} is busy with job {job.id} ({job.kind}, {job.state})")
        self.job = job


class EventHub:
    """Events numbered from 1, the last EVENTS_KEPT kept; each open stream has its own bounded queue. A stream that
    falls QUEUE_EVENTS behind is closed (a None in its queue) rather than let the studio's memory grow."""

    def __init__(self) -> None:
        self.events: deque[dict[str, Any]] = deque(maxlen=EVENTS_KEPT)
        self.queues: set[asyncio.Queue] = set()
        self.ids = itertools.count(1)

    def publish(self, event: dict[str, Any]) -> None:
        event = {"id": next(self.ids), "time": round(time.time(), 3), **event}
        self.events.append(event)
        for q in list(self.queues):
            try:
                q.put_nowait(event)
            except asyncio.QueueFull:
                self.queues.discard(q)
                with contextlib.suppress(asyncio.QueueFull):
                    q.get_nowait()
                    q.put_nowait(None)

    def subscribe(self, since: int = 0) -> asyncio.Queue:
        q: asyncio.Queue = asyncio.Queue(maxsize=QUEUE_EVENTS + EVENTS_KEPT)
        for e in self.events:
            if e["id"] > since:
                q.put_nowait(e)
        self.queues.add(q)
        return q

    def unsubscribe(self, q: asyncio.Queue) -> None:
        self.queues.discard(q)


class Jobs:
    """The studio's jobs by id, at most one active per scene. `start` checks and claims the scene without awaiting,
    so of many requests at once exactly one gets the scene and the others `Busy` with its id."""

    def __init__(self, root: Path, hub: EventHub):
        self.root, self.hub = Path(root), hub
        self.jobs: dict[str, Job] = {}
        self.by_scene: dict[str, str] = {}
        self.procs: dict[str, asyncio.subprocess.Process] = {}
        self.tasks: set[asyncio.Task] = set()

    def active(self, scene: str) -> Job | None:
        job = self.jobs.get(self.by_scene.get(scene, ""))
        return job if job is not None and job.active else None

    def start(self, scene: str, kind: str, argv: list[str]) -> Job:
        """Queue `wonderverse ARGV` for `scene`; Busy when the scene has an active job."""
        running = self.active(scene)
        if running is not None:
            raise Busy(running)
        job = Job(id=uuid.uuid4().hex[:12], scene=scene, kind=kind, argv=argv)
        self.jobs[job.id] = job
        self.by_scene[scene] = job.id
        self._state(job)
        task = asyncio.get_running_loop().create_task(self._run(job))
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return job

    def _state(self, job: Job) -> None:
        self.hub.publish({"type": "job", "job": job.id, "scene": job.scene, "kind": job.kind, **_state_of(job)})

    async def _run(self, job: Job) -> None:
        env = {k: v for k, v in os.environ.items() if k != CHILD_ENV}  # supervised: Ctrl-C, kills, reaper
        env.update({PROGRESS_ENV: "json", "PYTHONUNBUFFERED": "1"})
        try:
            proc = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "flows",
                *job.argv,
                stdin=asyncio.subprocess.DEVNULL,
                stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.STDOUT,
                env=env,
                cwd=self.root,
                limit=LINE_LIMIT,
            )
        except OSError as e:
            return self._end(job, None, f"the job could not start: {e.strerror or e}")
        self.procs[job.id] = proc
        job.pid, job.state = proc.pid, "running"
        self._state(job)
        assert proc.stdout is not None
        while True:
            try:
                raw = await proc.stdout.readline()
            except (ValueError, asyncio.LimitOverrunError):  # an over-long line: skipped, not fatal
                continue
            if not raw:
                break
            self._line(job, raw.decode("utf-8", "replace").rstrip("\r\n"))
        rc = await proc.wait()
        self.procs.pop(job.id, None)
        self._end(job, rc, None)

    def _line(self, job: Job, line: str) -> None:
        if line.startswith(JSON_PREFIX):
            try:
                event = json.loads(line[len(JSON_PREFIX) :])
            except ValueError:
                return
            if not isinstance(event, dict):
                return
            job.step = event.get("step") or job.step
            if event.get("event") == "progress":
                job.progress = {k: event.get(k) for k in ("done", "total", "unit", "note", "left_s", "line")}
            elif event.get("event") == "started":
                job.progress = None
            self.hub.publish({"type": "progress", "job": job.id, "scene": job.scene, **event})
            return
        if not line.strip():
            return
        if line.startswith("error: "):
            job.error = line[len("error: ") :]
        job.log.append(line)
        self.hub.publish({"type": "log", "job": job.id, "scene": job.scene, "line": line})

    def _end(self, job: Job, rc: int | None, error: str | None) -> None:
        job.returncode, job.ended = rc, time.time()
        job.state = "done" if rc == 0 else "failed"
        if job.state == "failed" and not job.error:
            if error is not None:
                job.error = error
            elif rc is not None and rc < 0:
                job.error = f"the job was killed by signal {-rc}; what was complete is kept in the scene"
            else:
                job.error = f"the job stopped with exit code {rc}"
        self._state(job)

    def kill_all(self) -> None:
        """Kill every running job with all its processes (the studio is stopping)."""
        import psutil

        for proc in list(self.procs.values()):
            try:
                parent = psutil.Process(proc.pid)
                tree = [parent, *parent.children(recursive=True)]
            except psutil.Error:  # already gone
                tree = []
            for p in tree:
                with contextlib.suppress(psutil.Error):
                    p.send_signal(signal.SIGKILL)


def _state_of(job: Job) -> dict[str, Any]:
    return {"state": job.state, "error": job.error, "returncode": job.returncode}
