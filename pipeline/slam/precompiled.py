"""The align iterations compiled ahead of time (AOTInductor packages), loaded without tracing.

torch.compile traces each function again in every process, its on-disk caches warm or not: on
the CPU 1-2.5 s a graph, once per pyramid level, and 7-9 s of the H200's 9-11 s warm-up
(bench/NOTES.md, Change 36). A package made once by torch.export and AOTInductor is a shared
library that a later process loads in ~10 ms (the CPU). Packages are kept in the user's cache
folder, one per function, input signature, constant arguments, source and build
(`package_key`). A missing one is built in a child process (`package_builds`) while this run
goes on with `fallback` (torch.compile'd) for that signature: the package serves later runs.
(This run's calls are recorded in CUDA graphs from its first frame, so a package finished
mid-run would not be called anyway.) An exported program is inference-only: the align
iterations (Gauss-Newton steps) need no gradient, and a loss (`joint`) is exported with its
backward traced ahead, its gradients scaled in an autograd function (`_PackagedLoss`).

A package that failed to build here before (its `.failed` note), or that fails to load, means
the fallback, said once in the log. A package is native code, as inductor's own cached kernels
are: it is only ever read from the user's own cache folder, never from a run folder.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
import os
import sys
import types
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import torch
from torch.utils._pytree import TreeSpec, tree_flatten, tree_unflatten

from pipeline.package_builds import BUILDS, BUILT_ELSEWHERE, BuildJob, TensorMeta, unit_tangent
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


def describe(leaf: Any) -> str:
    """What a package depends on of an argument: a tensor's shape, stride, dtype, device and
    whether it requires grad, any other argument's value (baked into the package)."""
    if isinstance(leaf, torch.Tensor):
        return f"{tuple(leaf.shape)}:{tuple(leaf.stride())}:{leaf.dtype}:{leaf.device}:{leaf.requires_grad}"
    return repr(leaf)


def package_key(name: str, source: str, signature: Sequence[Any]) -> str:
    """What a package depends on besides the build (the cache folder's name holds torch, CUDA and
    the device kind): the function's name and source digest, `signature` (the arguments'
    structure and each one `describe`d), and the C++ compiler it is built with (`CXX`: another
    compiler is tried afresh where one failed)."""
    parts = [name, source, sys.version.split()[0], os.environ.get("CXX", ""), *map(str, signature)]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:32]


Runner = Callable[..., Sequence[torch.Tensor | None]]


class _PackagedLoss(torch.autograd.Function):
    """A scalar loss from its joint package (`BuildJob.joint`): one call gives the loss and its
    gradients for a tangent of 1; the backward scales those by the loss's own gradient."""

    @staticmethod
    def forward(ctx: Any, runner: Runner, tangent: torch.Tensor, *tensors: torch.Tensor) -> torch.Tensor:
        loss, *gradients = (out for out in runner(*tensors, tangent) if out is not None)
        ctx.save_for_backward(*gradients)
        return loss

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        gradients = iter(ctx.saved_tensors)
        return None, None, *(next(gradients) * grad if needed else None for needed in ctx.needs_input_grad[2:])


@dataclass(frozen=True)
class _Loaded:
    runner: Runner
    state_spec: TreeSpec  # the structure the runner's outputs are put back into (its first argument's)
    tangent: torch.Tensor | None  # a joint package's: 1, of the loss's dtype, on its device


class Precompiled(Generic[State]):
    """`fn(state, *inputs) -> state` (tensors in pytrees, other arguments constants; `fn` at
    module level, for a child process to import) from its AOTInductor package in `folder`,
    built for later runs where missing while `fallback` runs; `built` counts the packages this
    instance had built, `loaded` those it found. With `joint`, `fn` is a scalar loss instead,
    differentiable with respect to its inputs that require grad: its package holds the forward
    and the backward (an exported program has no autograd), and the loss's dtype is that of the
    first of them."""

    def __init__(
        self, fn: Callable[..., State], name: str, folder: Path, fallback: Callable[..., State], joint: bool = False
    ) -> None:
        self.fn, self.name, self.folder, self.fallback, self.joint = fn, name, folder, fallback, joint
        self.source = source_digest(fn)
        self.built = self.loaded = 0
        self.failed = False
        self._runners: dict[tuple[Any, ...], _Loaded | None] = {}  # by signature (None: the fallback)

    def __call__(self, *args: Any) -> State:
        leaves, spec = tree_flatten(args)
        signature = (spec, *(describe(leaf) for leaf in leaves))
        if signature not in self._runners:
            self._runners[signature] = self._found(signature, leaves, spec)
        found = self._runners[signature]
        if found is None:
            return self.fallback(*args)
        tensors = [leaf for leaf in leaves if isinstance(leaf, torch.Tensor)]
        if found.tangent is not None:
            loss: State = _PackagedLoss.apply(found.runner, found.tangent, *tensors)
            return loss
        state: State = tree_unflatten(list(found.runner(*tensors)), found.state_spec)
        return state

    def _found(self, signature: tuple[Any, ...], leaves: list[Any], spec: TreeSpec) -> _Loaded | None:
        """The loaded package for the arguments `leaves` and `spec` (of `signature`), or None (the
        fallback; its build started)."""
        path = self.folder / f"{self.name}-{package_key(self.name, self.source, signature)}.pt2"
        job = BuildJob(self.fn, self.name, path, tuple(_meta(leaf) for leaf in leaves), spec, self.joint)
        if path.exists():
            return self._load(path, leaves, spec.child(0))  # (the first argument's structure)
        if job.failed_note.exists():
            self._refuse(job.failed_note.read_text(errors="replace").strip())
        elif not self.failed:
            try:
                self.folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:  # (a cache folder this user cannot write: nothing is built)
                self._refuse(f"its cache folder cannot be made: {exc}")
                return None
            BUILDS.start(job, self._built)
        return None

    def _load(self, path: Path, leaves: list[Any], state_spec: TreeSpec) -> _Loaded | None:
        from torch._inductor import aoti_load_package

        tensors = [leaf for leaf in leaves if isinstance(leaf, torch.Tensor)]
        device = next((t.device for t in tensors if t.device.type == "cuda"), None)
        try:
            with DEVICE_WIDE:  # (a load never beside another thread's compiled call or capture)
                runner: Runner = aoti_load_package(
                    str(path), device_index=device.index if device is not None and device.index is not None else -1
                )
        except Exception as exc:
            self._refuse(f"its package {path.name} did not load: {exc}")
            return None
        self.loaded += 1
        return _Loaded(runner, state_spec, unit_tangent(tensors) if self.joint else None)

    def _built(self, why_not: str) -> None:
        """A build this instance started ended ("": built; `BUILT_ELSEWHERE`: by another process)."""
        if why_not == BUILT_ELSEWHERE:
            log.debug("%s is being built ahead of time by another process", self.name)
        elif why_not:
            self._refuse(why_not)
        else:
            self.built += 1

    def _refuse(self, why: str) -> None:
        """The fallback from now on for what is not loaded yet, said once."""
        if not self.failed:
            self.failed = True
            log.warning("%s could not be compiled ahead of time (%s): torch.compile instead", self.name, why)


def _meta(leaf: Any) -> Any:
    return TensorMeta.of(leaf) if isinstance(leaf, torch.Tensor) else leaf
