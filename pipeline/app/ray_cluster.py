"""The Ray cluster that `bench --ray` and `serve --ray` run on: connecting (or starting a local
one) and what each cell or session declares.

Ray (the optional extra `cluster`) is imported only by the commands given `--ray`.
"""

from __future__ import annotations

import logging
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import ray

from pipeline.errors import UserError

log = logging.getLogger("gsplatam")

CPUS_PER_WORKER = 1  # each cell or session holds one CPU slot; its GPU share is what scales it


@dataclass(frozen=True)
class Cluster:
    address: str  # the cluster's GCS address (host:port), the one `ray start --address` takes
    nodes: list[dict[str, Any]]  # per live node: host, address, CPUs, GPUs
    gpus: float  # GPUs in the whole cluster

    @property
    def largest_node_gpus(self) -> float:
        return max((node["gpus"] for node in self.nodes), default=0.0)


@contextmanager
def connected(address: str | None) -> Iterator[Cluster]:
    """Connect to the cluster at `address` ("auto": the one this machine has joined), or start
    a local one for the command when `address` is None; disconnect at the end (a local cluster
    stops then). A connection this process already holds is used and left open."""
    owned = not ray.is_initialized()
    if owned:
        try:
            if address:
                ray.init(address=address, logging_level=logging.WARNING)
            else:
                with _interrupts_ignored_by_children():
                    ray.init(include_dashboard=False, logging_level=logging.WARNING)
        except (ConnectionError, ValueError) as exc:
            raise UserError(f"cannot connect to the Ray cluster at {address}: {exc}") from exc
    try:
        cluster = _describe()
        log.info("ray: cluster %s, %d nodes, %g GPUs", cluster.address, len(cluster.nodes), cluster.gpus)
        yield cluster
    finally:
        if owned:
            ray.shutdown()


@contextmanager
def _interrupts_ignored_by_children() -> Iterator[None]:
    """Start processes that ignore SIGINT (they inherit it). A terminal's Ctrl-C reaches the whole
    process group, which holds a local cluster's own servers: it must stop the sessions through
    the driver, not break the cluster under them."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _describe() -> Cluster:
    nodes = [
        {
            "host": node["NodeManagerHostname"],
            "address": node["NodeManagerAddress"],
            "cpus": node["Resources"].get("CPU", 0.0),
            "gpus": node["Resources"].get("GPU", 0.0),
        }
        for node in ray.nodes()
        if node["Alive"]
    ]
    return Cluster(ray.get_runtime_context().gcs_address, nodes, sum(n["gpus"] for n in nodes))


def check_gpu_share(gpus: float, what: str) -> None:
    """A GPU share Ray can schedule: a fraction up to 1 (several share a GPU) or a whole number."""
    if gpus < 0 or (gpus > 1 and not float(gpus).is_integer()):
        raise UserError(f"GPUs per {what} must be a fraction up to 1 or a whole number, not {gpus:g}")


def declared_resources(cluster: Cluster, gpus: float, what: str) -> dict[str, float]:
    """The Ray resources of one cell or session (`what`, for messages): `gpus` GPUs (checked by
    `check_gpu_share`) and one CPU. On a cluster without GPUs it declares the CPU alone, and says so."""
    if cluster.gpus == 0:
        log.warning("ray: the cluster has no GPU: each %s declares %d CPU and no GPU", what, CPUS_PER_WORKER)
        return {"num_cpus": CPUS_PER_WORKER, "num_gpus": 0}
    if gpus > cluster.largest_node_gpus:
        raise UserError(
            f"{gpus:g} GPUs per {what}, but no node of the cluster has more than {cluster.largest_node_gpus:g}"
        )
    return {"num_cpus": CPUS_PER_WORKER, "num_gpus": gpus}


def summary(cluster: Cluster, declared: dict[str, float]) -> dict[str, Any]:
    """The cluster as a report records it."""
    return {
        "address": cluster.address,
        "nodes": cluster.nodes,
        "declared": f"{declared['num_gpus']:g} GPU, {declared['num_cpus']:g} CPU",
    }


def cause_of(error: BaseException) -> BaseException:
    """The exception a Ray task or actor raised, out of Ray's wrapper; any other error as it is."""
    if isinstance(error, ray.exceptions.RayTaskError) and error.cause is not None:
        return error.cause
    return error
