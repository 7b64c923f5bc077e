"""`serve --ray`: several live sources in one service, each session a Ray actor.

Each actor runs the daemon's own `serve` (the same session, periodic saves and final save) for
one source on the GPU share it declares, into a run folder of its own on its node. This process,
the driver, follows them: one status endpoint lists every session; a session whose actor dies
(killed, crashed, its node lost) is started again by Ray, into a new run folder, up to
MAX_RESTARTS times; a session that fails is reported and the others go on. SIGINT or SIGTERM
asks every session to stop, and each finishes its frame and saves, as the daemon does.
"""

from __future__ import annotations

import asyncio
import logging
import signal
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

import ray

from pipeline.app.logs import configure_logging
from pipeline.app.ray_cluster import cause_of, check_gpu_share, connected, declared_resources
from pipeline.app.remote_control import RemoteControl
from pipeline.app.serve import serve_live
from pipeline.config import Config
from pipeline.devices import placement, resolve_device
from pipeline.errors import UserError
from pipeline.io.sources.cameras import live_camera, source_label
from pipeline.ui.status_http import serve_status

log = logging.getLogger("gsplatam")

MAX_RESTARTS = 2  # a session whose actor died is started again this often, each time into a new run folder
STATUS_EVERY_S = 1.0  # how often the driver asks each session for its status
STATUS_TIMEOUT_S = 5.0
RESTART_TIMEOUT_S = 120.0  # a restarting actor not back by then (no node with its GPU share free) has failed
ACTOR_THREADS = 4  # the session's run, and the driver's status and stop calls beside it
NAMESPACE = "gsplatam"  # the actors are named gsplatam:<session> in it (`ray list actors`)


class LiveSession:
    """One source's SLAM inside a Ray actor (`LiveSessionActor`): `run` holds one of its threads
    for the whole session while `status` and `stop` answer in the others. Its run folder is
    `name` under `output` (absolute: a worker's working folder is not the driver's)."""

    def __init__(self, name: str, spec: str, config: Config, output: str) -> None:
        configure_logging(f"gsplatam [{name}]")
        self.name, self.spec, self.config, self.output = name, spec, config, output
        self.control = RemoteControl()
        self.folder: str | None = None

    def run(self, attempt: int) -> dict[str, Any]:
        """The session, to its end or a stop -> its frames, Gaussians and run folder. `attempt` > 0
        (after a restart) starts a new map in a new folder: the last one keeps its last save."""
        name = f"{self.name}_restart{attempt}" if attempt else self.name
        self.folder = str(Path(self.output) / name)
        changes = [("run.name", name), ("run.output", self.output), ("live.status_port", 0)]  # the driver's status
        device = resolve_device(self.config.run.device)  # this node's
        result = serve_live(self.spec, self.config, device, progress=False, control=self.control, changes=changes)
        metrics = result.metrics
        return {
            "folder": str(result.folder.path),
            "frames": metrics.frames if metrics else 0,
            "gaussians": metrics.gaussians if metrics else 0,
        }

    def status(self) -> dict[str, Any]:
        """Where the session runs, its run folder and its live status (None until its graph runs)."""
        return {**placement(), "folder": self.folder, "live": self.control.status()}

    def stop(self) -> None:
        self.control.request_stop()


# Ray restarts a dead actor (a new process, __init__ again); the driver then calls `run` anew.
LiveSessionActor = ray.remote(max_restarts=MAX_RESTARTS)(LiveSession)


class SessionState(StrEnum):
    STARTING = "starting"
    RUNNING = "running"
    RESTARTING = "restarting"  # its actor died; Ray is starting it again
    STOPPING = "stopping"
    FINISHED = "finished"  # its source ended, or it stopped and saved
    STOPPED = "stopped"  # stopped while restarting: its last run folder holds its last save
    FAILED = "failed"


@dataclass
class RemoteSession:
    """The driver's view of one session."""

    name: str
    spec: str
    actor: Any  # the LiveSessionActor handle
    state: SessionState = SessionState.STARTING
    restarts: int = 0
    error: str | None = None
    status: dict[str, Any] | None = None  # the actor's last answer to `status`
    result: dict[str, Any] | None = None  # what `run` returned

    def view(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "source": self.spec,
            "state": self.state,
            "restarts": self.restarts,
            "error": self.error,
            **(self.status or {}),
            **({"result": self.result} if self.result else {}),
        }

    async def follow(self, stopping: asyncio.Event) -> None:
        """Run the session to its end; start it again when its actor died, unless stopping."""
        for attempt in range(MAX_RESTARTS + 1):
            if stopping.is_set() and attempt:  # stopped while restarting: nothing more to save
                self.state = SessionState.STOPPED
                return
            self.state = SessionState.RUNNING if not stopping.is_set() else SessionState.STOPPING
            try:
                self.result = await self.actor.run.remote(attempt)
                self.state = SessionState.FINISHED
                return
            except ray.exceptions.ActorUnavailableError as exc:  # Ray is restarting the actor
                self.error = _first_line(exc)
                if stopping.is_set() or attempt == MAX_RESTARTS:
                    break
                self.restarts += 1
                self.state = SessionState.RESTARTING
                log.warning("ray: session %s lost its actor (%s); starting it again", self.name, self.error)
                if not await self._restarted():
                    break
            except ray.exceptions.RayError as exc:  # the actor is gone for good, or the session failed
                self.error = _first_line(exc)
                break
        self.state = SessionState.FAILED
        log.error("ray: session %s failed: %s", self.name, self.error)

    async def _restarted(self) -> bool:
        """Wait until Ray has the actor back (its calls fail fast while it restarts) -> False when
        it is gone for good or not back within RESTART_TIMEOUT_S."""
        deadline = asyncio.get_running_loop().time() + RESTART_TIMEOUT_S
        while asyncio.get_running_loop().time() < deadline:
            try:
                await self.actor.status.remote()
                return True
            except ray.exceptions.ActorUnavailableError:
                await asyncio.sleep(STATUS_EVERY_S)
            except ray.exceptions.RayError as exc:
                self.error = _first_line(exc)
                return False
        return False

    async def watch(self) -> None:
        """Keep `status` fresh (a slow or restarting actor keeps its last answer)."""
        while True:
            try:
                self.status = await asyncio.wait_for(self.actor.status.remote(), STATUS_TIMEOUT_S)
            except (ray.exceptions.RayError, TimeoutError):
                pass
            await asyncio.sleep(STATUS_EVERY_S)

    def request_stop(self) -> None:
        """Ask a running session to stop (a restarting one is not started again: `follow`)."""
        if self.state in (SessionState.STARTING, SessionState.RUNNING):
            self.state = SessionState.STOPPING
            self.actor.stop.remote()


def _first_line(error: BaseException) -> str:
    cause = cause_of(error)
    lines = [line for line in str(cause).splitlines() if line.strip()]
    return f"{type(cause).__name__}: {lines[0] if lines else ''}"


def session_names(specs: list[str], config: Config) -> list[str]:
    """Each source's session name, its run folder's: `<run.name or live>_<source>`; a spec that
    is not a live camera's, or a bad address, is reported here, before any actor starts."""
    prefix = config.run.name or "live"
    names: list[str] = []
    for index, spec in enumerate(specs):
        camera, address = live_camera(spec)
        camera.check(address)
        name = f"{prefix}_{source_label(spec)}"
        names.append(f"{name}_{index}" if name in names else name)
    return names


def serve_on_ray(specs: list[str], config: Config, address: str | None, gpus_per_session: float) -> int:
    """Serve every source as a session on the cluster until SIGINT/SIGTERM or until every session
    ended; -> 0, or 1 when a session failed."""
    if config.viewer.enabled:
        raise UserError("--viewer is not available with --ray")
    names = session_names(specs, config)
    output = str(Path(config.run.output).resolve())
    check_gpu_share(gpus_per_session, "session")
    with connected(address) as cluster:
        declared = declared_resources(cluster, gpus_per_session, "session")
        sessions = [
            RemoteSession(name, spec, _start_actor(name, spec, config, output, declared))
            for name, spec in zip(names, specs)
        ]
        log.info("ray: %d sessions (%s each); Ctrl-C stops and saves them all", len(sessions), declared)
        asyncio.run(_drive(sessions, config))
    for session in sessions:
        result = session.result or {}
        outcome = (
            f"failed: {session.error}" if session.state == SessionState.FAILED else f"{result.get('frames', 0)} frames"
        )
        print(f"{session.name}: {outcome}, {result.get('gaussians', 0):,} Gaussians: {result.get('folder', '-')}/")
    return 1 if any(s.state == SessionState.FAILED for s in sessions) else 0


def _start_actor(name: str, spec: str, config: Config, output: str, declared: dict[str, float]) -> Any:
    options = {"name": f"gsplatam:{name}", "namespace": NAMESPACE, "max_concurrency": ACTOR_THREADS, **declared}
    return LiveSessionActor.options(**options).remote(name, spec, config, output)


async def _drive(sessions: list[RemoteSession], config: Config) -> None:
    """Follow every session, with the status endpoint, until all ended or a signal stops them."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        async with asyncio.TaskGroup() as group:
            followers = [group.create_task(s.follow(stop)) for s in sessions]
            helpers = [group.create_task(s.watch()) for s in sessions]
            if config.live.status_port:
                read = board(sessions)
                endpoint = serve_status(config.live.status_host, config.live.status_port, read, stop)
                helpers.append(group.create_task(endpoint))
            ended: asyncio.Future[Any] = asyncio.gather(*followers)
            stopped: asyncio.Future[Any] = group.create_task(stop.wait())
            await asyncio.wait({ended, stopped}, return_when=asyncio.FIRST_COMPLETED)
            if stop.is_set():
                log.info("ray: stopping every session (each finishes its frame and saves)")
                for session in sessions:
                    session.request_stop()
            await ended
            for task in [stopped, *helpers]:
                task.cancel()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


def board(sessions: list[RemoteSession]) -> Callable[[], dict[str, Any]]:
    """The driver's status: every session, with its state and its own live status."""

    def read() -> dict[str, Any]:
        states = [s.state for s in sessions]
        return {
            "sessions": [s.view() for s in sessions],
            "running": states.count(SessionState.RUNNING),
            "failed": states.count(SessionState.FAILED),
        }

    return read
