"""The run folder: every file a run, its profile, its recording and its exports write is named,
written, read and removed here and nowhere else."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from pipeline import __version__
from pipeline.config import Config, load_config, to_toml
from pipeline.errors import DataError, OutputError
from pipeline.io.files.atomic import (
    TEMPORARY_PREFIX,
    atomic_export,
    atomic_write_all,
    atomic_write_text,
    bytes_writer,
    temporaries_of,
)
from pipeline.io.files.folders import inside
from pipeline.io.files.g2o import G2oEdge, g2o_text
from pipeline.io.files.trajectory import tum_trajectory_text
from pipeline.io.outputs.checkpoint import LEGACY_NAME, checkpoint_bytes, read_checkpoint
from pipeline.io.outputs.exports import EXPORTERS
from pipeline.io.outputs.exports.nerfstudio import WRITTEN as NERFSTUDIO_FILES
from pipeline.io.outputs.exports_record import ExportsRecord, text_of
from pipeline.io.outputs.frame_row import COLUMNS, EARLIER_WIDTH, FrameRow
from pipeline.io.outputs.intrinsics import CameraIntrinsics, read_intrinsics
from pipeline.io.outputs.ply import gaussian_ply_bytes, write_ply
from pipeline.io.outputs.run_description import RunDescription
from pipeline.io.outputs.run_lock import LOCK_NAME, RunLock
from pipeline.io.outputs.run_metrics import RunMetrics
from pipeline.io.sources.live.recording import COLOR_LIST
from pipeline.io.sources.live.recording import WRITTEN as RECORDING_FILES
from pipeline.render.types import Gaussians
from pipeline.slam.loops.pose_graph import chained
from pipeline.slam.state import Checkpoint, LoopState

RESULTS = (
    "frames.csv", "metrics.json", "trajectory.txt", "groundtruth.txt", "map.ply", "checkpoint.safetensors",
    "trace.json", "profile.txt", "intrinsics.json", "exports.json", "trajectory_as_tracked.txt", "pose_graph.g2o",
    "trajectory.png", "renders",
)  # fmt: skip
RECORDING = "recording"  # serve's live.record: the input in the TUM layout
MARKER = ".gsplatam-run"  # written when a run starts in a folder: what makes it a run folder of this tool
MARKER_FORMAT = "gsplatam.run"
# The folders a run or an export fills, with what it writes into each (globs in the folder).
FILLED_FOLDERS = {
    RECORDING: RECORDING_FILES,
    EXPORTERS["nerfstudio"].DEFAULT_NAME: NERFSTUDIO_FILES,
    "renders": ("frame*.png",),
}


class RunFolder:
    """The files of one run in an existing folder: config, per-frame CSV, metrics, trajectories,
    map, checkpoint, camera, profile, recording and exports. An `--overwrite` removes exactly
    these (`remove_earlier_run`): a user's own files beside them stay."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.config = path / "config.toml"
        self.frames_csv = path / "frames.csv"
        self.metrics = path / "metrics.json"
        self.trajectory = path / "trajectory.txt"  # estimated camera-to-world, TUM format
        self.groundtruth = path / "groundtruth.txt"  # reference camera-to-world, TUM format
        self.trajectory_as_tracked = path / "trajectory_as_tracked.txt"  # with loop closure: before its corrections
        self.pose_graph = path / "pose_graph.g2o"  # with loop closure: the keyframe pose graph (g2o's format)
        self.map = path / "map.ply"
        self.trajectory_plot = path / "trajectory.png"  # the trajectory against the reference (pictures.py)
        self.renders = path / "renders"  # the evaluated frames' renders beside the input (pictures.py)
        self.checkpoint = path / "checkpoint.safetensors"
        self.intrinsics = path / "intrinsics.json"  # the camera at SLAM's working size (IntrinsicsRecorder)
        self.trace = path / "trace.json"  # --profile: the torch profiler's Chrome trace
        self.profile = path / "profile.txt"  # --profile: per-stage times, top kernels and host calls
        self.recording = path / RECORDING  # a TUM dataset: `gsplatam run` reads it
        self.marker = path / MARKER  # this is a run folder of gsplatam (`--overwrite` acts on no other)
        self.lock = path / LOCK_NAME  # held while a process writes the folder (run_lock.py)
        defaults = {fmt: exporter.DEFAULT_NAME for fmt, exporter in EXPORTERS.items()}
        self.exports = ExportsRecord(path, defaults)  # each export's path and the map it came from
        self.exports_record = self.exports.path
        self._frames_file: IO[str] | None = None

    @staticmethod
    def existing(path: Path) -> RunFolder:
        """A run folder written before (DataError when `path` holds no checkpoint)."""
        folder = RunFolder(path)
        if not folder.checkpoint.is_file():
            raise DataError(f"{path} is not a run folder (no {folder.checkpoint.name})")
        return folder

    @contextlib.contextmanager
    def claimed(self) -> Iterator[RunFolder]:
        """This folder, locked while the caller writes it (RunFolderBusy, naming the holder,
        while another process does). The folder must exist."""
        with RunLock(self.path):
            yield self

    def is_run(self) -> bool:
        """Whether the folder is a run folder of this tool: it carries the run marker, or (made by
        a version before the marker) it holds both config.toml and frames.csv."""
        if self.marker.is_file() and not self.marker.is_symlink():
            return True
        return self.config.is_file() and self.frames_csv.is_file()

    def mark(self) -> None:
        """Write the run marker (the folder is a run folder of this tool)."""
        marker = {"format": MARKER_FORMAT, "version": __version__}
        with _writing(self.marker):
            atomic_write_text(self.marker, json.dumps(marker) + "\n")

    def holds_results(self) -> bool:
        """Whether a run saved anything here: a checkpoint (its first save) or a recording."""
        return self.checkpoint.is_file() or self.recorded()

    def owns(self, path: Path) -> bool:
        """Whether `path` is one of the files only a run writes here (its results, config,
        marker, lock, or anything in its recording): an export never writes onto one."""
        if path == self.path or not path.is_relative_to(self.path):
            return False
        return path.relative_to(self.path).parts[0] in {*RESULTS, self.config.name, MARKER, LOCK_NAME, RECORDING}

    def remove_unfinished(self) -> None:
        """Remove what a run that saved nothing wrote (config, frames.csv, marker, lock, ...),
        then the folder if nothing else is left in it."""
        self.remove_earlier_run()
        for path in (self.marker, self.lock):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        with contextlib.suppress(OSError):
            self.path.rmdir()

    def export(self, fmt: str) -> Path:
        """Where `gsplatam export --to fmt` writes by default."""
        return self.path / EXPORTERS[fmt].DEFAULT_NAME

    def recorded(self) -> bool:
        """Whether the folder holds a live session's recording (a dataset `gsplatam run` reads)."""
        return (self.recording / COLOR_LIST).is_file()

    def earlier_run(self) -> list[str]:
        """The names of what an earlier run (or an export of it) left here; [] for none."""
        names = [*RESULTS, RECORDING, *(e.DEFAULT_NAME for e in EXPORTERS.values())]
        return [name for name in dict.fromkeys(names) if (self.path / name).exists()]

    def remove_earlier_run(self) -> None:
        """Remove what an earlier run and its exports wrote (its config, `earlier_run`, the files
        they put into their folders, temporary files left by a kill), and nothing else: no path
        is followed through a link (a link among them is removed itself)."""
        recorded = [(path, NERFSTUDIO_FILES if fmt == "nerfstudio" else None) for fmt, path in self.exports.inside()]
        named = [(self.path / name, FILLED_FOLDERS.get(name)) for name in [self.config.name, *self.earlier_run()]]
        for path, filled in [*recorded, *named]:
            if path.is_symlink():  # the link goes, never what it points at
                path.unlink()
            elif filled is not None and path.is_dir():
                _remove_filled(path, filled)
            elif path.is_file():
                path.unlink()
        for path in self._temporaries():  # files, and folders of a killed multi-file export
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()

    def _temporaries(self) -> set[Path]:
        """The temporary files and folders this tool left in the folder (a kill mid-write): those
        of its prefix, and those an earlier version named after a file of a run (a user's own
        `.notes.tmp` is neither)."""
        names = [*RESULTS, self.config.name, MARKER, RECORDING, *(e.DEFAULT_NAME for e in EXPORTERS.values())]
        patterns = [f"{TEMPORARY_PREFIX}*.tmp", *(p for name in names for p in temporaries_of(name))]
        return {path for pattern in patterns for path in self.path.glob(pattern)}

    def exports_made(self) -> dict[str, Any]:
        """exports.json: format -> {path, frames, frames_mapped, gaussians, map_version[, stale]};
        {} where there is none; rebuilt (and reported) where it is not sound."""
        return self.exports.read()[0]

    def record_export(self, fmt: str, target: Path, checkpoint: Checkpoint) -> None:
        """Note in exports.json that `target` holds `fmt` of the map of `checkpoint` (under the
        record's lock: exports made at once each keep their entry)."""
        entry = {
            "path": str(target.relative_to(self.path) if target.is_relative_to(self.path) else target.absolute()),
            "frames": checkpoint.frames_done,
            "frames_mapped": checkpoint.mapping.frames_seen,
            "gaussians": len(checkpoint.gaussians),
            "map_version": self._map_version(checkpoint.frames_done),
        }
        with _writing(self.exports_record), self.exports.locked():
            record, _ = self.exports.read()
            self.exports.write({**record, fmt: entry})

    def _mark_stale(self, record: dict[str, Any], checkpoint: Checkpoint) -> bool:
        """Mark every export of `record` made of another map than `checkpoint`'s stale. -> whether
        any was marked (none where there is no export, or all are marked already)."""
        changed = False
        for entry in record.values():
            if "stale" not in entry and (entry.get("frames"), entry.get("gaussians")) != (
                checkpoint.frames_done,
                len(checkpoint.gaussians),
            ):
                entry["stale"] = f"made from {entry.get('frames')} frames; the map now holds {checkpoint.frames_done}"
                changed = True
        return changed

    def _map_version(self, frames_done: int) -> int | None:
        """The map version frames.csv gives the last of the first `frames_done` frames."""
        kept = [row for row in self._frame_rows() if int(row["index"]) < frames_done]
        return int(kept[-1]["map_version"]) if kept and (kept[-1]["map_version"] or "").isdigit() else None

    def frame_timestamps(self) -> dict[int, float]:
        """Frame index -> its timestamp in seconds, as frames.csv gives it ({} where it cannot be read)."""
        stamps = {}
        for row in self._frame_rows():
            with contextlib.suppress(TypeError, ValueError):
                stamps[int(row["index"])] = float(row["timestamp"])
        return stamps

    def _frame_rows(self) -> list[dict[str, str]]:
        """frames.csv's rows with a frame index; [] where it cannot be read."""
        try:
            with open(self.frames_csv, newline="") as f:
                return [row for row in csv.DictReader(f) if (row.get("index") or "").isdigit()]
        except (OSError, UnicodeDecodeError, csv.Error):
            return []

    def write_config(self, config: Config) -> None:
        with _writing(self.config):
            atomic_write_text(self.config, to_toml(config))

    def read_config(self) -> Config:
        """The run's config.toml (UserError naming it when it is missing or not a config)."""
        return load_config(config_file=self.config)

    def append_frame(self, row: FrameRow) -> None:
        """One CSV line, flushed at once: the one file appended to rather than replaced, so a
        kill loses no line written before it (a line cut off by a full disk is dropped by
        `keep_frames` on resume)."""
        if self._frames_file is None:
            new = not self.frames_csv.exists() or self.frames_csv.stat().st_size == 0
            fd = os.open(self.frames_csv, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o644)
            self._frames_file = open(fd, "a", newline="")  # never through a link
            if new:
                csv.writer(self._frames_file).writerow(COLUMNS)
        csv.writer(self._frames_file).writerow(row.cells())
        self._frames_file.flush()

    def close(self) -> None:
        frames_file, self._frames_file = self._frames_file, None
        if frames_file is not None:
            frames_file.close()

    def keep_frames(self, frames_done: int) -> None:
        """Drop the frames.csv lines of frames after the first `frames_done` (written after the
        checkpoint a resume continues from) and any incomplete last line."""
        if not self.frames_csv.exists():
            return
        lines = self.frames_csv.read_text(errors="replace").splitlines(keepends=True)
        rows = [row for line in lines if line.endswith("\n") and (row := _row(line)) and int(row[0]) < frames_done]
        table = io.StringIO()
        csv.writer(table).writerows([COLUMNS, *rows])
        with _writing(self.frames_csv):
            atomic_write_text(self.frames_csv, table.getvalue())

    def write_state(
        self, checkpoint: Checkpoint, run: RunDescription, timestamps: np.ndarray, reference: np.ndarray | None
    ) -> None:
        """Trajectory (and reference), map and checkpoint of the run `run` describes, from a
        SLAM checkpoint on the host; `timestamps` [N] seconds and `reference` [N, 4, 4]
        camera-to-world per pose. All are replaced, or (a write failing, e.g. on a full disk)
        none: the last complete set stays. The checkpoint is replaced last: a process killed
        while the files are replaced one by one leaves the others one save ahead of it, never
        behind, and a resume (which starts from the checkpoint) rewrites them all."""
        files = {
            self.trajectory: tum_trajectory_text(timestamps, checkpoint.poses.double().numpy()).encode(),
            self.map: gaussian_ply_bytes(checkpoint.gaussians),
        }
        if reference is not None:
            files[self.groundtruth] = tum_trajectory_text(timestamps, reference).encode()
        if (loops := checkpoint.mapping.loops) is not None:
            tracked = checkpoint.tracking.tracked_poses
            tracked = checkpoint.poses if tracked is None else tracked
            files[self.trajectory_as_tracked] = tum_trajectory_text(timestamps, tracked.double().numpy()).encode()
            files[self.pose_graph] = pose_graph_text(loops).encode()
        checkpoint_data = checkpoint_bytes(checkpoint, run)
        with self.exports.locked():
            record, rebuilt = self.exports.read()
            if self._mark_stale(record, checkpoint) or rebuilt:
                files[self.exports_record] = text_of(record).encode()
            files[self.checkpoint] = checkpoint_data  # last: see above
            atomic_write_all({path: bytes_writer(data) for path, data in files.items()})
        if loops is None:  # a resume without loop closure: its files would describe a shorter run
            for path in (self.trajectory_as_tracked, self.pose_graph):
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()

    def write_map(self, gaussians: Gaussians) -> None:
        write_ply(self.map, gaussians)

    def read_checkpoint(self) -> tuple[Checkpoint, RunDescription]:
        """-> (the checkpoint, the run it was saved by); DataError if there is none or it is
        not one this version reads."""
        legacy = self.path / LEGACY_NAME
        if not self.checkpoint.exists() and legacy.exists():
            raise DataError(
                f"{legacy} is a checkpoint of gsplatam 0.1, a pickle, which is never loaded (unpickling can run "
                f"code): run the sequence again to get {self.checkpoint.name}"
            )
        return read_checkpoint(self.checkpoint)

    def read_intrinsics(self) -> CameraIntrinsics:
        return read_intrinsics(self.intrinsics)

    def read_metrics(self) -> RunMetrics | None:
        """metrics.json as any version wrote it, or None where there is none (or it cannot be read)."""
        try:
            return RunMetrics.from_json(json.loads(self.metrics.read_text()))
        except (OSError, ValueError, TypeError):
            return None

    def write_metrics(self, metrics: RunMetrics) -> None:
        with _writing(self.metrics):
            atomic_write_text(self.metrics, _json(metrics.to_json()))

    def write_trace(self, export: Callable[[Path], None]) -> None:
        """The profiler's Chrome trace, which `export` writes to the path it is given."""
        atomic_export(self.trace, export)

    def write_profile(self, text: str) -> None:
        atomic_write_text(self.profile, text)


def run_owning(path: Path) -> RunFolder | None:
    """The run folder (a run of this tool, or a folder holding a checkpoint) among `path`'s
    parents of which `path` is one of its own files (`RunFolder.owns`), or None. The rule of what
    may be written where: a run folder's own files are written by its run only."""
    for parent in path.parents:
        folder = RunFolder(parent)
        if folder.owns(path) and (folder.is_run() or folder.checkpoint.is_file()):
            return folder
    return None


def _json(value: Any) -> str:
    return json.dumps(value, indent=2, sort_keys=True) + "\n"


def _remove_filled(folder: Path, written: tuple[str, ...]) -> None:
    """Remove the files matching `written` (and their temporary files) from `folder`, then the
    folders left empty: a folder holding anything else stays with it. Nothing is reached through
    a link."""
    for pattern in (*written, *(p for name in written for p in temporaries_of(name))):
        for path in folder.glob(pattern):
            if inside(folder, path.relative_to(folder)) is not None and (path.is_file() or path.is_symlink()):
                path.unlink()
    for path in sorted((p for p in folder.rglob("*") if p.is_dir() and not p.is_symlink()), reverse=True):
        with contextlib.suppress(OSError):
            path.rmdir()
    with contextlib.suppress(OSError):
        folder.rmdir()


@contextlib.contextmanager
def _writing(path: Path) -> Iterator[None]:
    """An OSError writing `path` as the OutputError a user sees (one line, exit code 2)."""
    try:
        yield
    except OSError as exc:
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}") from None


def pose_graph_text(loops: LoopState) -> str:
    """Loop closure's keyframe pose graph in g2o's format: every keyframe kept, the odometry
    edges and the loop edges the optimum kept."""
    graph = chained(loops.node_c2w, loops.odometry_information, tuple(loops.loops))
    edges = [G2oEdge(e.first, e.second, e.relative, e.information) for e in graph.edges]
    return g2o_text(graph.c2w, edges)


def _row(line: str) -> list[str]:
    """A frames.csv line's cells in today's columns (one of an earlier layout, without the solve's
    columns, padded with empty cells); [] for the header or a malformed line."""
    fields = next(csv.reader([line]), [])
    if len(fields) not in (EARLIER_WIDTH, len(COLUMNS)) or not fields[0].isdigit():
        return []
    return fields + [""] * (len(COLUMNS) - len(fields))
