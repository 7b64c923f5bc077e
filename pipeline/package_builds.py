"""AOTInductor packages built in child processes, beside the run that wants them.

A build (torch.export, AOTInductor's C++ compile, a first load) takes about a minute on the
H200's host and 10-60 s on a CPU, mostly in one Python thread and one compiler process; seven
one after the other made a first run 7-10 minutes longer (bench/NOTES.md, Change 36). Here each
build is a child process of its own (`BUILDER`), up to `MAX_BUILDS` at once, started in a
session of its own so that an interrupt of the run does not lose it; the run goes on with its
torch.compile'd fallback meanwhile. The child writes the package under a partial name, loads it
once (a package whose shared library does not fit the process's C++ runtime kills whatever
loads it: SIGSEGV on the H200 at da7c30a), and only then renames it into place, so that a
package in the cache folder has been loaded once on this machine. A build that fails for a
reason that would fail again (an exception, a crash, a hang past `BUILD_TIMEOUT_S`) leaves a
`.failed` note beside where the package would be, naming why; later runs read it and do not
build again (a change of source, shapes or compiler is another package and is tried afresh). A
`joint` build holds a scalar loss's forward and backward (`_JointCall`). A child claims its
package first (a `.building` file naming it): with loops on, the mapping process's loop search
wants the tracking process's align iterations at the same sizes and the same moment (the first
keyframe), as do two runs on one machine, and the second child to claim one leaves it to the
first (`BUILT_ELSEWHERE`). A child notes an exception's failure itself, so that a build that outlives
its run (the mapping process ends before its builds) still spares later runs the same failure.

The job reaches the child on its standard input, pickled: from this process, never from disk.
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch.utils._pytree import TreeSpec, tree_flatten, tree_leaves, tree_unflatten

from pipeline.io.files.atomic import atomic_write_text

log = logging.getLogger("gsplatam")

BUILDER = "from pipeline.package_builds import build_from_stdin; build_from_stdin()"
BUILD_TIMEOUT_S = 1800  # one build on two busy CPU cores; a hang past it is a failure
MAX_BUILDS = max(1, (os.cpu_count() or 2) // 2)  # each holds about one core (and, on CUDA, a context)
# Inductor compiles a graph's kernels in a pool of workers, one per core (at most 32) unless told:
# MAX_BUILDS builds with a pool each would put 8 x 16 workers on the H200 host's 16 cores, beside
# the run's own compiles. Each build's pool is two workers, its share of the cores.
BUILD_COMPILE_THREADS = "2"
INTERRUPTED = {signal.SIGINT, signal.SIGTERM, signal.SIGKILL, signal.SIGHUP}  # a build stopped, not failed
ELSEWHERE_EXIT = 75  # a child's exit status where another child holds the package's claim
BUILT_ELSEWHERE = "another process is building it"  # what `done` is told then: not a failure


class TensorMeta(NamedTuple):
    """What an export needs of an input tensor: it traces with fake tensors, never the values."""

    shape: tuple[int, ...]
    stride: tuple[int, ...]
    dtype: torch.dtype
    device: str
    requires_grad: bool = False  # (a joint build differentiates its result with respect to it)

    @staticmethod
    def of(tensor: torch.Tensor) -> TensorMeta:
        meta = tuple(tensor.shape), tuple(tensor.stride()), tensor.dtype, str(tensor.device), tensor.requires_grad
        return TensorMeta(*meta)

    def example(self) -> torch.Tensor:
        example = torch.empty_strided(self.shape, self.stride, dtype=self.dtype, device=self.device).zero_()
        return example.requires_grad_(self.requires_grad)


@dataclass(frozen=True)
class BuildJob:
    """`fn(*tree_unflatten(leaves, spec))` (a function a child can import: module level) as an
    AOTInductor package at `path`; tensors among `leaves` as `TensorMeta`."""

    fn: Callable[..., Any]
    name: str
    path: Path
    leaves: tuple[Any, ...]
    spec: TreeSpec
    joint: bool = False  # `fn` returns a scalar: the package gives it and its gradients (`_JointCall`)

    @property
    def failed_note(self) -> Path:
        return self.path.with_suffix(".failed")

    @property
    def claim(self) -> Path:
        """Held by the child building the package (its process id inside) while it builds."""
        return self.path.with_suffix(".building")

    def partial(self, pid: int) -> Path:
        """Where the child `pid` writes the package until it has loaded it (AOTInductor wants .pt2)."""
        return self.path.with_name(f".{self.path.stem}.{pid}.partial.pt2")


class _FlatCall(torch.nn.Module):
    """`fn` over flat tensors: the export's input and output are tensors only (a package keeps
    no Python structure); the other arguments are constants of the program. `fn` returns the
    structure of its first argument (the caller rebuilds it so), or with `scalar` one tensor."""

    def __init__(self, fn: Callable[..., Any], leaves: Sequence[Any], spec: TreeSpec, scalar: bool) -> None:
        super().__init__()
        self.fn, self.leaves, self.spec, self.scalar = fn, list(leaves), spec, scalar

    def forward(self, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        given = iter(tensors)
        leaves = [next(given) if isinstance(leaf, torch.Tensor) else leaf for leaf in self.leaves]
        args = tree_unflatten(leaves, self.spec)
        result = self.fn(*args)
        if self.scalar and isinstance(result, torch.Tensor) and result.dim() == 0:
            return (result,)
        out, out_spec = tree_flatten(result)
        if self.scalar or out_spec != tree_flatten(args[0])[1]:
            wanted = "a scalar tensor" if self.scalar else "its first argument's structure"
            raise TypeError(f"{self.fn} does not return {wanted}")
        return tuple(out)


class _JointCall(torch.nn.Module):
    """A scalar function's forward and backward in one graph (AOTAutograd's joint graph: an
    exported program is inference-only, so the backward is traced here, ahead): flat tensors and
    the result's tangent in, the result and the gradient of each input that requires grad out."""

    def __init__(self, flat: _FlatCall, tensors: tuple[torch.Tensor, ...]) -> None:
        super().__init__()
        from torch._functorch.aot_autograd import aot_export_joint_simple

        self.graph = aot_export_joint_simple(flat, tensors, trace_joint=True)

    def forward(self, *tensors_and_tangent: torch.Tensor) -> tuple[torch.Tensor, ...]:
        *tensors, tangent = tensors_and_tangent
        return tuple(out for out in tree_leaves(self.graph(list(tensors), [tangent])) if out is not None)


def unit_tangent(tensors: Sequence[torch.Tensor]) -> torch.Tensor:
    """A joint package's tangent for its loss, 1: of the dtype and on the device of the first of
    `tensors` that requires grad (the loss's, in the losses made so)."""
    differentiated = next(t for t in tensors if t.requires_grad)
    return torch.ones((), dtype=differentiated.dtype, device=differentiated.device)


class ClaimedElsewhere(Exception):
    """Another living process builds this package."""


def claim(job: BuildJob) -> None:
    """Take `job`'s claim for this process, or raise `ClaimedElsewhere`. A claim whose process
    has ended, or older than `BUILD_TIMEOUT_S` (its process id may have been reused), is stale
    and taken over."""
    for attempt in range(2):
        try:
            descriptor = os.open(job.claim, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if attempt or _claim_is_live(job.claim):
                raise ClaimedElsewhere(str(job.claim)) from None
            job.claim.unlink(missing_ok=True)
            continue
        with os.fdopen(descriptor, "w") as claimed:
            claimed.write(f"{os.getpid()}\n")
        return


def _claim_is_live(path: Path) -> bool:
    try:
        holder, age = path.read_text().strip(), time.time() - path.stat().st_mtime
    except OSError:  # (released meanwhile)
        return False
    if age > BUILD_TIMEOUT_S:
        return False
    if not holder.isdigit():  # (its holder is writing it)
        return True
    try:
        os.kill(int(holder), 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # (another user's process: alive)
        pass
    return True


def build(job: BuildJob) -> None:
    """Claim, export, compile and load `job`'s function, then put the package in place (in the
    child)."""
    claim(job)
    try:
        _build_claimed(job)
    finally:
        job.claim.unlink(missing_ok=True)


def _build_claimed(job: BuildJob) -> None:
    from torch._inductor import aoti_compile_and_package, aoti_load_package

    leaves = [leaf.example() if isinstance(leaf, TensorMeta) else leaf for leaf in job.leaves]
    tensors = tuple(leaf for leaf in leaves if isinstance(leaf, torch.Tensor))
    flat = _FlatCall(job.fn, leaves, job.spec, scalar=job.joint)
    module: torch.nn.Module = flat
    if job.joint:
        module = _JointCall(flat, tensors)
        tensors = (*(t.detach() for t in tensors), unit_tangent(tensors))
    partial = job.partial(os.getpid())
    try:
        with torch.no_grad():
            program = torch.export.export(module, tensors, strict=False)
            aoti_compile_and_package(program, package_path=str(partial))
        aoti_load_package(str(partial))  # a library that does not fit this runtime crashes here, not in a run
        os.replace(partial, job.path)
    finally:
        partial.unlink(missing_ok=True)


def build_from_stdin() -> None:
    """A child's whole work: the job pickled on standard input (by its parent), built; a failure
    ends it with the exception's first line as the last line of its standard error."""
    job: BuildJob = pickle.load(sys.stdin.buffer)
    try:
        build(job)
    except ClaimedElsewhere:
        sys.exit(ELSEWHERE_EXIT)
    except Exception as exc:
        lines = str(exc).strip().splitlines()
        sys.exit(_failed(job, f"{type(exc).__name__}: {lines[0] if lines else ''}"))


class PackageBuilds:
    """The builds this process started: at most `MAX_BUILDS` running, the others queued. Each
    running one has a thread that waits for its child and calls the job's `done(reason)`
    ("" when built)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._queued: list[tuple[BuildJob, Callable[[str], None]]] = []
        self._running: dict[Path, threading.Thread] = {}
        self._started: set[Path] = set()

    def start(self, job: BuildJob, done: Callable[[str], None]) -> None:
        """Build `job` in a child process (once per package path in this process)."""
        with self._lock:
            if job.path in self._started:
                return
            self._started.add(job.path)
            self._queued.append((job, done))
            self._next()

    def pending(self) -> int:
        with self._lock:
            return len(self._queued) + len(self._running)

    def wait(self, should_stop: Callable[[], bool] = lambda: False, poll_s: float = 0.2) -> bool:
        """Until every build started has ended (True) or `should_stop()` (False)."""
        while self.pending():
            if should_stop():
                return False
            time.sleep(poll_s)
        return True

    def _next(self) -> None:
        """Start queued builds while fewer than `MAX_BUILDS` run (under the lock)."""
        while self._queued and len(self._running) < MAX_BUILDS:
            job, done = self._queued.pop(0)
            thread = threading.Thread(target=self._run, args=(job, done), name=f"build-{job.name}", daemon=True)
            self._running[job.path] = thread
            thread.start()

    def _run(self, job: BuildJob, done: Callable[[str], None]) -> None:
        """Build `job`, tell `done`, then count it ended (so that `wait` returns after `done`)."""
        try:
            try:
                reason = _child_build(job)
            except Exception as exc:  # (the child could not even be started)
                reason = f"its build could not be started: {exc}"
            done(reason)
        finally:
            with self._lock:
                del self._running[job.path]
                self._next()


def _child_build(job: BuildJob) -> str:
    """Run `job` in a child process; -> "" when built, else why not (a `.failed` note written
    where the same build would fail again)."""
    began = time.monotonic()
    child = subprocess.Popen(
        [sys.executable, "-c", BUILDER],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,  # an interrupt of the run (the terminal's process group) lets it finish
        env={
            "TORCHINDUCTOR_COMPILE_THREADS": BUILD_COMPILE_THREADS,  # (unless the user set it)
            **os.environ,
            "PYTHONPATH": os.pathsep.join(p for p in sys.path if p),  # it imports what this process can
        },
    )
    try:
        _, errors = child.communicate(pickle.dumps(job), timeout=BUILD_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        child.kill()
        child.communicate()
        job.partial(child.pid).unlink(missing_ok=True)
        return _failed(job, f"its build did not finish within {BUILD_TIMEOUT_S} s")
    job.partial(child.pid).unlink(missing_ok=True)  # (a child killed mid-write leaves it)
    if child.returncode == 0:
        log.info("%s built ahead of time in %.0f s: later runs load it", job.name, time.monotonic() - began)
        return ""
    if child.returncode == ELSEWHERE_EXIT:
        return BUILT_ELSEWHERE
    if child.returncode < 0:
        killed = signal.Signals(-child.returncode)
        compiler = f"; built with CXX={os.environ['CXX']}" if "CXX" in os.environ else ""  # (the H200's cause)
        why = f"its build died of {killed.name}{compiler}"
        return why if killed in INTERRUPTED else _failed(job, why)
    lines = errors.decode(errors="replace").strip().splitlines()
    return _failed(job, lines[-1] if lines else f"its build exited with {child.returncode}")


def _failed(job: BuildJob, why: str) -> str:
    """`why`, noted beside the package for later runs where the folder takes it."""
    try:
        atomic_write_text(job.failed_note, why + "\n")
    except OSError as exc:
        log.debug("could not note why %s was not built: %s", job.path.name, exc)
    return why


BUILDS = PackageBuilds()  # this process's


def wait_for_builds(should_stop: Callable[[], bool] = lambda: False) -> None:
    """At the end of a run: wait for the packages still being built, saying so; `should_stop()`
    leaves them to finish on their own (each in a session of its own)."""
    pending = BUILDS.pending()
    if not pending:
        return
    log.info(
        "waiting for %d ahead-of-time package(s) still being built for later runs (an interrupt leaves them to finish alone)",
        pending,
    )
    if not BUILDS.wait(should_stop):
        log.info("left %d package build(s) to finish in the background", BUILDS.pending())
