"""The align iterations compiled ahead of time (AOTInductor packages), loaded without tracing.

torch.compile traces each function again in every process, its on-disk caches warm or not: on
the CPU 1-2.5 s a graph, once per pyramid level, and 7-9 s of the H200's 9-11 s warm-up
(bench/NOTES.md, Change 36). A package made once by torch.export and AOTInductor is a shared
library that a later process loads in ~10 ms (the CPU). Packages are kept in the user's cache
folder, one per function, input signature, constant arguments, source and build
(`package_key`); a missing one is built (export and compile: longer than torch.compile's first
compile) and written whole or not at all. An exported program is inference-only, so only
functions that need no gradient are made so: the align iterations (Gauss-Newton steps).

A function whose export or build fails runs its `fallback` instead (torch.compile'd), said once
in the log. So does one whose new package fails to load in a child process (`trial_load`): a
package's shared library that does not fit the process's C++ runtime crashes whatever loads it,
which no `except` can catch (SIGSEGV on the H200 at da7c30a, where the image's `CXX` links
libstdc++ into the library statically: bench/NOTES.md, Change 36). A package is native code, as
inductor's own cached kernels are: it is only ever read from the user's own cache folder, never
from a run folder.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
import os
import signal
import subprocess
import sys
import types
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Generic, TypeVar

import torch
from torch.utils._pytree import TreeSpec, tree_flatten, tree_unflatten

from pipeline.slam.cuda_graphs import DEVICE_WIDE

log = logging.getLogger("gsplatam")

State = TypeVar("State")
PACKAGE = "pipeline"  # modules of this package count in a function's source digest


def source_modules(fn: Callable[..., Any]) -> dict[str, types.ModuleType]:
    """`fn`'s module and every module of this package it reaches through module globals (the
    functions and classes it imports, theirs in turn), by name."""
    root = inspect.getmodule(inspect.unwrap(fn))
    seen: dict[str, types.ModuleType] = {}
    todo = [root] if root is not None else []
    while todo:
        module = todo.pop()
        if module.__name__ in seen:
            continue
        seen[module.__name__] = module
        for value in vars(module).values():
            owner = value if inspect.ismodule(value) else inspect.getmodule(value)
            if owner is not None and owner.__name__.split(".")[0] == PACKAGE and owner.__name__ not in seen:
                todo.append(owner)
    return seen


def source_digest(fn: Callable[..., Any]) -> str:
    """sha256 of the source files of `source_modules(fn)`: a package built from other code is
    never loaded."""
    digest = hashlib.sha256()
    for name, module in sorted(source_modules(fn).items()):
        digest.update(name.encode())
        digest.update(Path(module.__file__ or "").read_bytes())
    return digest.hexdigest()


def package_key(name: str, source: str, leaves: Sequence[Any], spec: TreeSpec) -> str:
    """What a package depends on besides the build (the cache folder's name holds torch, CUDA and
    the device): the function's name and source digest, the arguments' structure, each tensor's
    shape, dtype and device, and every other argument's value (baked into the package)."""
    parts = [name, source, str(spec), sys.version.split()[0]]
    for leaf in leaves:
        if isinstance(leaf, torch.Tensor):
            parts.append(f"{tuple(leaf.shape)}:{leaf.dtype}:{leaf.device.type}:{tuple(leaf.stride())}")
        else:
            parts.append(repr(leaf))
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]


TRIAL_LOAD = "import sys; from torch._inductor import aoti_load_package; aoti_load_package(sys.argv[1])"
TRIAL_TIMEOUT_S = 300  # a start of Python and torch, and one load (seconds on a CPU)


def trial_load(path: Path) -> None:
    """Load the package at `path` in a child process; RuntimeError, saying how, where it fails."""
    try:
        command = [sys.executable, "-c", TRIAL_LOAD, str(path)]
        done = subprocess.run(command, capture_output=True, text=True, check=False, timeout=TRIAL_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"its package did not load in a child process within {TRIAL_TIMEOUT_S} s") from None
    if done.returncode == 0:
        return
    how = f"signal {signal.Signals(-done.returncode).name}" if done.returncode < 0 else f"exit {done.returncode}"
    compiler = f"; built with CXX={os.environ['CXX']}" if "CXX" in os.environ else ""  # (the H200's cause)
    raise RuntimeError(f"its package could not be loaded in a child process ({how}{compiler})")


def _signature(leaf: Any) -> Any:
    """What `package_key` reads of an argument, as a hashable value."""
    if isinstance(leaf, torch.Tensor):
        return leaf.shape, leaf.dtype, leaf.device, leaf.stride()
    return leaf


class _FlatCall(torch.nn.Module):
    """`fn` over flat tensors: the export's input and output are tensors only (a package keeps
    no Python structure); the other arguments are constants of the program."""

    def __init__(self, fn: Callable[..., Any], leaves: Sequence[Any], spec: TreeSpec) -> None:
        super().__init__()
        self.fn, self.leaves, self.spec = fn, list(leaves), spec
        self.state_spec: TreeSpec | None = None

    def forward(self, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        given = iter(tensors)
        leaves = [next(given) if isinstance(leaf, torch.Tensor) else leaf for leaf in self.leaves]
        args = tree_unflatten(leaves, self.spec)
        out, out_spec = tree_flatten(self.fn(*args))
        if out_spec != tree_flatten(args[0])[1]:
            raise TypeError(f"{self.fn} returns a structure other than its first argument's")
        return tuple(out)


class Precompiled(Generic[State]):
    """`fn(state, *inputs) -> state` (tensors in pytrees, other arguments constants) from its
    AOTInductor package in `folder`, built where missing; `built` counts the packages this
    instance built, `loaded` those it found."""

    def __init__(self, fn: Callable[..., State], name: str, folder: Path, fallback: Callable[..., State]) -> None:
        self.fn, self.name, self.folder, self.fallback = fn, name, folder, fallback
        self.source = source_digest(fn)
        self.built = self.loaded = 0
        self.failed = False
        # by `_signature`s: the package's runner, and the structure of the state it returns
        self._runners: dict[tuple[Any, ...], tuple[Callable[..., Sequence[torch.Tensor]], TreeSpec]] = {}

    def __call__(self, *args: Any) -> State:
        if self.failed:
            return self.fallback(*args)
        leaves, spec = tree_flatten(args)
        signature = (spec, *(_signature(leaf) for leaf in leaves))  # cheaper than the key, checked each call
        found = self._runners.get(signature)
        if found is None:
            key = package_key(self.name, self.source, leaves, spec)
            try:
                with DEVICE_WIDE:  # an export traces with FX: never beside another thread's compiled call
                    found = self._runners[signature] = (self._runner(key, leaves, spec), tree_flatten(args[0])[1])
            except Exception as exc:  # an operation export or AOTInductor refuses: compiled as before
                self.failed = True
                log.warning("%s could not be compiled ahead of time (%s): torch.compile instead", self.name, exc)
                return self.fallback(*args)
        runner, state_spec = found
        tensors = [leaf for leaf in leaves if isinstance(leaf, torch.Tensor)]
        state: State = tree_unflatten(list(runner(*tensors)), state_spec)
        return state

    def _runner(self, key: str, leaves: Sequence[Any], spec: TreeSpec) -> Callable[..., Sequence[torch.Tensor]]:
        from torch._inductor import aoti_compile_and_package, aoti_load_package

        path = self.folder / f"{self.name}-{key}.pt2"
        tensors = tuple(leaf for leaf in leaves if isinstance(leaf, torch.Tensor))
        if path.exists():
            self.loaded += 1
        else:
            self.folder.mkdir(parents=True, exist_ok=True)
            with torch.no_grad():
                program = torch.export.export(_FlatCall(self.fn, leaves, spec), tensors, strict=False)
                partial = path.with_name(f".{path.stem}.{os.getpid()}.partial.pt2")  # (it must end .pt2)
                try:
                    aoti_compile_and_package(program, package_path=str(partial))
                    trial_load(partial)
                    os.replace(partial, path)  # whole or not at all: a run stopped mid-build leaves no package
                finally:
                    partial.unlink(missing_ok=True)
            self.built += 1
        device = next((t.device for t in tensors if t.device.type == "cuda"), None)
        runner: Callable[..., Sequence[torch.Tensor]] = aoti_load_package(
            str(path), device_index=device.index if device is not None and device.index is not None else -1
        )
        return runner
