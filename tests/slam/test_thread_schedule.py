"""The thread schedule: the process schedule's mapping side in a thread of this process."""

from __future__ import annotations

import json
import multiprocessing
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch
import torch._functorch.config as functorch_config

from pipeline.app.cli import main
from pipeline.io.outputs.checkpoint import read_checkpoint
from pipeline.slam import cuda_graphs
from pipeline.slam.kernels import make_kernels
from pipeline.slam.mapping.backend import MappingBackend
from pipeline.slam.process.mapping_thread import ThreadLock
from pipeline.stages.sinks import ResultSink

FAST = ["tracking.iters=3", "mapping.iters=3", "slam.schedule=thread", "run.save_every_s=1e9"]


def _run_argv(dataset: Path, output: Path, extra: list[str]) -> list[str]:
    sets = [f"--set={s}" for s in FAST + extra]
    return ["run", str(dataset), "--preset", "tiny", "--device", "cpu", "--quiet", "--output", str(output),
            "--name", "r", *sets]  # fmt: skip


def _saved_rows(folder: Path) -> list[int]:
    return [int(line.split(",")[0]) for line in (folder / "frames.csv").read_text().splitlines()[1:]]


@pytest.mark.parametrize("compiled", [False, True])
def test_the_compiler_is_imported_before_the_mapping_thread_starts(compiled: bool) -> None:
    """Two threads importing torch's compiler at once deadlock (the H200 at 055e532): the tracking
    thread imports what either side's first compile would, and only the compiler a run uses."""
    probe = (
        "import sys, torch; from pipeline.slam.process.mapping_thread import import_the_compiler; "
        "wanted = ('torch._dynamo', 'torch._inductor.compile_fx'); before = [m in sys.modules for m in wanted]; "
        f"import_the_compiler({compiled}); print(before, [m in sys.modules for m in wanted])"
    )
    said = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.strip()
    assert said == f"[False, False] [True, {compiled}]"


def test_the_lock_takes_multiprocessing_timeouts() -> None:
    lock = ThreadLock()
    assert lock.acquire(timeout=None)
    assert not lock.acquire(timeout=0.01) and not lock.acquire(block=False, timeout=5)
    lock.release()
    with lock:
        assert not lock.acquire(block=False)


def test_a_device_wide_wait_never_overlaps_another_threads_recording(monkeypatch: pytest.MonkeyPatch) -> None:
    """While one thread records a graph (holds DEVICE_WIDE), another's wait for the device waits
    for the recording to end: waiting on a stream under capture would spoil it."""
    events: list[str] = []
    monkeypatch.setattr(cuda_graphs.torch.cuda, "synchronize", lambda device=None: events.append("synchronized"))
    recording, waiting = threading.Event(), threading.Event()

    def record() -> None:
        with cuda_graphs.DEVICE_WIDE:
            recording.set()
            waiting.wait(5)
            events.append("recorded")

    recorder = threading.Thread(target=record)
    recorder.start()
    recording.wait(5)
    waiter = threading.Thread(target=cuda_graphs.synchronize_device)
    waiter.start()
    waiter.join(0.2)  # the waiter is blocked on the lock meanwhile
    waiting.set()
    recorder.join(5)
    waiter.join(5)
    assert events == ["recorded", "synchronized"]


@pytest.mark.slow
def test_every_compiled_kernel_is_called_one_thread_at_a_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """A compile in one thread fails any other thread's compiled call (FX's tracing flag is
    process-wide; measured on the H200 at 6a71ace): each compiled kernel holds DEVICE_WIDE
    while it runs, and the backward is compiled with the forward, inside that call."""

    def held_elsewhere() -> bool:  # whether another thread finds the lock taken
        taken: list[bool] = []

        def probe() -> None:
            free = cuda_graphs.DEVICE_WIDE.acquire(blocking=False)
            taken.append(not free)
            if free:
                cuda_graphs.DEVICE_WIDE.release()

        prober = threading.Thread(target=probe)
        prober.start()
        prober.join()
        return taken[0]

    monkeypatch.setattr(torch, "compile", lambda fn, dynamic: lambda *args: held_elsewhere())
    monkeypatch.setattr(functorch_config, "force_non_lazy_backward_lowering", False)
    kernels = make_kernels(compiled=True)
    assert functorch_config.force_non_lazy_backward_lowering
    compiled: list[Callable[..., object]] = [
        kernels.tracking_loss,
        kernels.mapping_loss,
        kernels.align.one,
        kernels.align.batch,
    ]
    for kernel in compiled:  # each the stand-in above: whether the lock was held during the call
        assert kernel()
    assert not held_elsewhere()


def test_mapping_runs_in_a_thread_of_this_process(
    replica_seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every frame tracked and mapped, with no second process, by a thread named for it."""
    consume = ResultSink.consume
    seen: list[tuple[list[str], list[str]]] = []

    def consume_and_look(self: ResultSink, result: Any) -> None:
        consume(self, result)
        threads = [t.name for t in threading.enumerate() if t.name == "gsplatam-mapping"]
        seen.append((threads, [p.name for p in multiprocessing.active_children()]))

    monkeypatch.setattr(ResultSink, "consume", consume_and_look)
    assert main(_run_argv(replica_seq, tmp_path, ["mapping.rate=frame"])) == 0
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert metrics["schedule"] == "thread" and metrics["frames"] == 6
    assert metrics["mapping_process"]["frames_mapped"] == 6 and metrics["ate"]["rmse_cm"] < 5
    assert len(seen) == 6 and all(threads == ["gsplatam-mapping"] and not children for threads, children in seen)
    assert not [t for t in threading.enumerate() if t.name == "gsplatam-mapping"]  # ended with the run


@pytest.mark.slow
@pytest.mark.parametrize("how", ["raises", "hangs"])
def test_a_failing_mapping_thread_leaves_a_complete_resumable_run(
    replica_seq: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    how: str,
) -> None:
    """Mapping's third frame raises, or hangs past slam.backend_timeout_s (a thread cannot be
    killed: it is left behind): one line naming the mapping thread, exit code 1, every frame
    tracked so far saved with the last complete map; --resume finishes the run."""
    original = MappingBackend.map
    calls: list[int] = []
    release = threading.Event()

    def failing_map(self: MappingBackend, tracked: Any, is_last: bool = False) -> Any:
        calls.append(tracked.frame.index)
        if len(calls) == 3:
            if how == "hangs":
                release.wait(60)  # no sign of life meanwhile
            raise RuntimeError("mapping broke")
        return original(self, tracked, is_last)

    monkeypatch.setattr(MappingBackend, "map", failing_map)
    try:
        code = main(_run_argv(replica_seq, tmp_path, ["mapping.rate=frame", "slam.backend_timeout_s=2"]))
    finally:
        release.set()  # the thread left behind ends
    assert code == 1
    error = capsys.readouterr().err.strip().splitlines()[-1]
    why = "failed: RuntimeError: mapping broke" if how == "raises" else "has shown no sign of life"
    assert f"the mapping thread {why}" in error
    folder = tmp_path / "r"
    saved, _ = read_checkpoint(folder / "checkpoint.safetensors")
    assert 2 <= saved.frames_done and saved.mapping.frames_seen <= saved.frames_done
    assert _saved_rows(folder) == list(range(saved.frames_done))

    monkeypatch.setattr(MappingBackend, "map", original)
    assert main(["run", "--resume", str(folder), "--quiet", "--device", "cpu"]) == 0
    resumed = json.loads((folder / "metrics.json").read_text())
    assert resumed["frames"] == 6 and resumed["stopped"] is None and resumed["schedule"] == "thread"
    assert _saved_rows(folder) == list(range(6))
