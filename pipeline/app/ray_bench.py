"""`bench --ray`: the benchmark matrix with each cell a Ray task, on a local or an existing cluster.

A task runs the same `run_cell` as a local bench (the same `run_slam`), on whichever node has
the GPU share it declares; it returns its row through Ray, so the JSON and the table are written
here, on the driver, as for a local run. Dataset folders are passed as absolute paths, which every
node must be able to read; the generated rooms are made on the worker, in its runs folder. A cell
that fails, or whose worker dies, is a row with its error; the others go on.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import ray
import torch

from pipeline.app.bench import report_of
from pipeline.app.bench_cell import Cell, bench_device, failed_row, run_cell
from pipeline.app.ray_cluster import cause_of, check_gpu_share, connected, declared_resources, summary

log = logging.getLogger("gsplatam")


@ray.remote(max_retries=1)  # a worker or node that dies is retried once; an error in the cell is its row
def _cell_task(cell: Cell, base_overrides: list[str], runs: str, profile: bool) -> dict[str, Any]:
    return run_cell(cell, base_overrides, Path(runs), bench_device(base_overrides), progress=False, profile=profile)


def run_matrix_on_ray(
    cells: list[Cell],
    base_overrides: list[str],
    runs: Path,
    address: str | None,
    gpus_per_cell: float,
    device: torch.device,
    profile: bool = False,
) -> dict[str, Any]:
    """Run every cell as a Ray task (on its node's device) -> the same report as `run_matrix`,
    rows in matrix order, each with the node and GPU it ran on; run folders go under `runs` on
    the node of each cell. `device` is this machine's, for the report."""
    check_gpu_share(gpus_per_cell, "cell")
    with connected(address) as cluster:
        declared = declared_resources(cluster, gpus_per_cell, "cell")
        task = _cell_task.options(**declared)
        start = time.perf_counter()
        pending = {
            task.remote(cell, base_overrides, str(runs.resolve()), profile): index for index, cell in enumerate(cells)
        }
        rows: dict[int, dict[str, Any]] = {}
        while pending:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            index = pending.pop(ref)
            rows[index] = _row(ref, cells[index])
            log.info(
                "bench: %d of %d cells done (%s on %s%s)",
                len(rows),
                len(cells),
                cells[index].name,
                rows[index].get("node") or "a lost worker",
                f": {rows[index]['error']}" if rows[index]["error"] else "",
            )
        return report_of(
            [rows[i] for i in range(len(cells))],
            base_overrides,
            profile,
            time.perf_counter() - start,
            device,
            cluster=summary(cluster, declared),
        )


def _row(ref: ray.ObjectRef, cell: Cell) -> dict[str, Any]:
    """The cell's row, or, when its worker died, a row with that error."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayError as exc:
        return {**failed_row(cell, cause_of(exc)), "node": None, "gpu": None, "wall_s": None}
