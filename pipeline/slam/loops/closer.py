"""Loop closure inside the mapping side: a node of the keyframe pose graph for every keyframe
kept, the loop search at each (`detection.detect_loops`) and at each frame tracking lost
(`frame_lost`: a node only where its loop closes), and, when the graph's optimum keeps an
accepted loop, the corrected keyframe poses with the map moved along.

Each Gaussian remembers the node of the keyframe that created it (`LoopState.creator`): one
seeded by a frame that becomes a keyframe belongs to that keyframe's node; one seeded by another
frame to the newest keyframe's (the frame was tracked against the map around it, and tracking
follows that keyframe: `Trajectory.poses_with`). A correction moves every Gaussian rigidly
with its node's correction, c2w_new @ inv(c2w_old); mapping then re-fits where old and new
parts of the map overlap.

Odometry edges join consecutive nodes. Their relative poses are the current estimates, derived
again before each optimisation (so that mapping's refinement of keyframe poses counts); their
information is the normal equations of the new keyframe's alignment to the previous one at that
relative pose (`LoopSearch.odometry`), or the soft `odometry_sigma_*` where that judged the step unsound.

With loop closure off (`loops.enabled` false) the mapping side holds a `NoLoopCloser`: the same
calls, doing nothing.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import torch

from pipeline.config import LoopConfig, TrackingConfig
from pipeline.render.types import Gaussians
from pipeline.slam.cuda_graphs import synchronize_device
from pipeline.slam.keyframes import Keyframe, sample_valid_pixels
from pipeline.slam.loops.detection import ClosedLoop, LoopDetection, closed_loop_line
from pipeline.slam.loops.map_correction import corrections, move_map
from pipeline.slam.loops.pose_graph import Edge, PoseGraph, chained, fixed_information, motion_size, optimise
from pipeline.slam.loops.search import LoopSearch
from pipeline.slam.state import LoopState
from pipeline.slam.tracking.rgbd_alignment import EAGER_ALIGN, AlignKernels, SourcePoints

log = logging.getLogger("gsplatam")
F64 = torch.float64


@dataclass(frozen=True)
class Correction:
    """A loop closed: every node's pose before and after, and the record."""

    old_c2w: torch.Tensor  # [K, 4, 4] float64 camera-to-world per node, before
    node_c2w: torch.Tensor  # [K, 4, 4] float64: after (the optimum)
    closed: ClosedLoop  # its published_s still 0
    started: float  # time.perf_counter() when the detection began


def queued_work_done(device: torch.device) -> float:
    """Seconds until `device` has run the work queued before a search (the mapping side's, which
    under `process` shares the GPU with the tracking process), counted apart: a search's own time
    then starts on an idle queue, where its first host read would otherwise wait for it."""
    if device.type != "cuda":
        return 0.0
    started = time.perf_counter()
    synchronize_device(device)
    return time.perf_counter() - started


class LoopCloser:
    searches_lost_frames = True  # a frame tracking lost is searched for a loop (`frame_lost`)

    def __init__(
        self,
        config: LoopConfig,
        tracking: TrackingConfig,
        samples: int,
        seed: int,
        kernels: AlignKernels = EAGER_ALIGN,
    ) -> None:
        """`kernels`: the alignment's Levenberg-Marquardt iteration, from one start and from a
        batch (the compiled ones where `run.compile` says so, as the tracker's)."""
        self.config = config
        self.tracking = tracking
        self.samples = samples  # pixels sampled for the candidates' overlap (keyframes.overlap_samples)
        self.seed = seed
        self.kernels = kernels
        self.state = LoopState.empty()
        self.search = LoopSearch(config, tracking, kernels)
        self._unpublished: Correction | None = None  # a loop closed whose corrected map is not yet published

    def restore(self, saved: LoopState | None, gaussians: int, device: torch.device) -> None:
        """Continue from `saved` (None: a checkpoint without loop closure's state: a graph that
        starts at the next keyframe, the `gaussians` already in the map owned by no node)."""
        if saved is None:
            saved = replace(LoopState.empty(), creator=torch.full((gaussians,), -1, dtype=torch.int64))
        self.state = replace(saved, creator=saved.creator.to(device), node_positions=list(saved.node_positions))
        self.search = LoopSearch(self.config, self.tracking, self.kernels)  # its sightings are not saved

    def saved(self, keyframes: list[Keyframe]) -> LoopState:
        """A host copy of the state, its nodes at the stored `keyframes`' current poses."""
        state = self.state
        return replace(
            state,
            creator=state.creator.cpu(),
            node_c2w=self.graph_poses(keyframes),
            node_positions=list(state.node_positions),
            loops=list(state.loops),
            closed=list(state.closed),
        )

    def graph_poses(self, keyframes: list[Keyframe]) -> torch.Tensor:
        """[K, 4, 4] float64 of the nodes: the stored keyframes' current poses, the last known of the others."""
        c2w = self.state.node_c2w.clone()
        node_of = self.state.node_of()
        for keyframe in keyframes:
            if keyframe.pose.position in node_of:
                c2w[node_of[keyframe.pose.position]] = keyframe.c2w.detach().to("cpu", F64)
        return c2w

    def creator_node(self, keeps: bool) -> int:
        """The node the Gaussians seeded now belong to: the keyframe about to be kept, else the newest."""
        return len(self.state.node_positions) - (0 if keeps else 1)

    def seeded(self, count: int, keeps: bool, device: torch.device) -> None:
        """`count` Gaussians were appended to the map (see `creator_node`)."""
        added = torch.full((count,), self.creator_node(keeps), dtype=torch.int64, device=device)
        self.state.creator = torch.cat([self.state.creator.to(device), added])

    def kept(self, positions: torch.Tensor | None) -> None:
        """The map was cut to the Gaussians at `positions` [M] (None: no change)."""
        if positions is not None:
            self.state.creator = self.state.creator[positions.to(self.state.creator.device)]

    def close_loops(
        self, gaussians: Gaussians, keyframes: list[Keyframe], intrinsics: torch.Tensor
    ) -> tuple[Gaussians, list[Keyframe]]:
        """The newest of `keyframes` (the store, oldest first) was just kept (`keyframe_kept`);
        -> the map and the store, moved with the corrected poses when a loop closed (recorded
        when that map is published: `map_published`), else as they were."""
        return self._corrected(gaussians, keyframes, self.keyframe_kept(keyframes, intrinsics))

    def frame_lost(
        self, gaussians: Gaussians, keyframes: list[Keyframe], lost: Keyframe, intrinsics: torch.Tensor
    ) -> tuple[Gaussians, list[Keyframe]] | None:
        """A frame tracking judged lost (`lost`, at the pose it was given), searched for a loop as a
        keyframe would be: on a loop whose estimates drifted far, the revisit's frames are lost
        (tracked against a map that puts the place seen again metres away) exactly where the loop
        is, so a search from keyframes alone never sees it. Its step from the newest keyframe is
        measured first against that keyframe's image (`LoopSearch.step_from_previous`); where a
        loop is accepted, the frame becomes a keyframe (a node of the graph; it seeds no Gaussian)
        at that pose and the loop is closed. -> the map and the store (the frame kept, oldest
        first, moved with the correction, recorded when that map is published), or None: no
        loop accepted, or the graph's optimum dropped it (the frame's node is taken out again,
        so that a view placed by its step from a drifted keyframe never joins the map's
        keyframes); nothing changed but the tally and the sightings kept for the next search."""
        if not keyframes:
            return None
        waited = queued_work_done(lost.depth.device)
        started = time.perf_counter()
        trial = [*keyframes, lost]
        sources = self.search.kept(trial, intrinsics)
        step = self.search.step_from_previous(trial, sources, intrinsics)
        if not step.failure:
            previous = keyframes[-1].c2w.detach().to("cpu", F64)
            trial[-1] = replace(lost, c2w=(previous @ step.relative).to(lost.c2w))
        detection = self._detect(trial, sources, intrinsics, started, waited, lost=True)
        if not detection.accepted:
            return None
        before = replace(self.state, node_positions=list(self.state.node_positions), loops=list(self.state.loops))
        self._add_node(trial, sources, intrinsics)
        correction = self._closed(trial, detection, started)
        if correction is None:  # the optimum dropped its loops: a frame placed by its step alone is no keyframe
            self.state = replace(before, tally=self.state.tally)
            return None
        return self._corrected(gaussians, trial, correction)

    def _corrected(
        self, gaussians: Gaussians, keyframes: list[Keyframe], correction: Correction | None
    ) -> tuple[Gaussians, list[Keyframe]]:
        """The map and the store moved by `correction` (None: as they are), kept to be recorded
        when that map is published."""
        if correction is None:
            return gaussians, keyframes
        self._unpublished = correction
        moved = move_map(gaussians, self.state.creator, correction.old_c2w, correction.node_c2w)
        node_of = self.state.node_of()
        return moved, [replace(k, c2w=correction.node_c2w[node_of[k.pose.position]].to(k.c2w)) for k in keyframes]

    def map_published(self, device: torch.device) -> tuple[ClosedLoop, ...]:
        """The map is published: -> the loop closed in it (recorded, with the time from its
        detection's start until now, and logged), if any."""
        correction, self._unpublished = self._unpublished, None
        if correction is None:
            return ()
        if device.type == "cuda":
            synchronize_device(device)  # once per loop closed: its times are the GPU's too
        closed = self.published(correction)
        log.info(closed_loop_line(closed))  # a mapping process configures no logging: its client logs the report
        return (closed,)

    def keyframe_kept(self, keyframes: list[Keyframe], intrinsics: torch.Tensor) -> Correction | None:
        """The newest of `keyframes` (the store, oldest first) was just kept: its node and
        odometry edge, then the loop search; -> the correction when a loop is closed. The
        search's warm-up (the first keyframe's, `LoopSearch.warm_up`) is not counted as a search."""
        waited = queued_work_done(keyframes[-1].depth.device)
        started = time.perf_counter()
        sources = self.search.kept(keyframes, intrinsics)
        if self.search.warm_up(keyframes, sources, intrinsics):
            started = time.perf_counter()
        self._add_node(keyframes, sources, intrinsics)
        return self._closed(keyframes, self._detect(keyframes, sources, intrinsics, started, waited), started)

    def _add_node(self, keyframes: list[Keyframe], sources: list[SourcePoints], intrinsics: torch.Tensor) -> None:
        """The newest of `keyframes` (`sources`: its pyramid as points) becomes the graph's newest
        node, with its odometry edge from the node before."""
        state, node, current = self.state, len(self.state.node_positions), keyframes[-1]
        state.node_positions.append(current.pose.position)
        state.node_c2w = torch.cat([state.node_c2w, current.c2w.detach().to("cpu", F64)[None]])
        state.odometry_information = torch.cat(
            [state.odometry_information, self._odometry(keyframes, sources, intrinsics, node)[None]]
        )

    def _detect(
        self,
        keyframes: list[Keyframe],
        sources: list[SourcePoints],
        intrinsics: torch.Tensor,
        started: float,
        waited: float,
        lost: bool = False,
    ) -> LoopDetection:
        """The loop search of the newest of `keyframes` (the node it has or would have; `lost`: a
        frame tracking lost), counted with the `waited` seconds before it (`queued_work_done`)."""
        node = len(self.state.node_positions) - (keyframes[-1].pose.position in self.state.node_of())
        generator = torch.Generator().manual_seed(self.seed + node)  # no state to keep: one draw per node
        pixels = sample_valid_pixels(keyframes[-1].depth, self.samples, generator)
        detection = self.search.detect(keyframes, sources, intrinsics, pixels, lost)
        self.state.tally = self.state.tally.counted(detection, time.perf_counter() - started, waited)
        return detection

    def _closed(self, keyframes: list[Keyframe], detection: LoopDetection, started: float) -> Correction | None:
        """The graph, with the accepted loops of `detection` (from the newest node, the newest of
        `keyframes`), optimised: -> the correction where its optimum moved the nodes."""
        state = self.state
        node_of = state.node_of()
        node = node_of[keyframes[-1].pose.position]
        found = [
            replace(edge, first=node_of[keyframes[edge.first].pose.position], second=node) for edge in detection.edges()
        ]
        if not found:
            return None
        detected = time.perf_counter()
        current = keyframes[-1]
        graph = self._graph(keyframes, [*state.loops, *found])
        solution = optimise(graph, self.config)
        state.tally = state.tally.optimised(solution)
        state.loops = [edge for edge in solution.graph.edges if edge.loop]
        kept_now = [e for e in solution.kept if e.second == node]
        if not kept_now:  # the optimum drops this search's loops: the graph as it was (its earlier loops hold already)
            return None
        state.node_c2w = solution.c2w
        moves = corrections(graph.c2w, solution.c2w)
        largest = max((motion_size(c) for c in moves), key=lambda size: size.translation_m)
        matched = tuple(self._frame_of(e.first, keyframes) for e in kept_now)
        seconds = time.perf_counter()
        closed = ClosedLoop(current.index, matched, largest, detected - started, seconds - detected, 0.0)
        return Correction(graph.c2w, solution.c2w, closed, started)

    def published(self, correction: Correction) -> ClosedLoop:
        """The corrected map of `correction` is published now: -> its record, kept in the state."""
        closed = replace(correction.closed, published_s=time.perf_counter() - correction.started)
        self.state.closed.append(closed)
        return closed

    def _frame_of(self, node: int, keyframes: list[Keyframe]) -> int:
        """The frame index of a node's keyframe (its position where it left the store)."""
        position = self.state.node_positions[node]
        return next((k.index for k in keyframes if k.pose.position == position), position)

    def _odometry(
        self, keyframes: list[Keyframe], sources: list[SourcePoints], intrinsics: torch.Tensor, node: int
    ) -> torch.Tensor:
        """The information [6, 6] of the edge from the keyframe before the newest (node - 1: the
        store keeps its newest keyframes) to the newest (`sources`: its pyramid as points;
        `LoopSearch.odometry`); where that judged the estimates' step unsound (tracked wrong,
        as on fast motion), `odometry_sigma_*`: a soft edge, where a loop's correction may go,
        rather than one as stiff as a sound step's; zeros for the first node."""
        if node == 0:
            return torch.zeros(6, 6, dtype=F64)
        verification = self.search.odometry(keyframes, sources, intrinsics)
        if verification.failure:
            return fixed_information(self.config.odometry_sigma_m, self.config.odometry_sigma_deg)
        return verification.information

    def _graph(self, keyframes: list[Keyframe], loops: list[Edge]) -> PoseGraph:
        """Nodes at the current estimates (stored keyframes' poses, the last known of the others),
        odometry edges at the relative poses they imply, and `loops`."""
        return chained(self.graph_poses(keyframes), self.state.odometry_information, tuple(loops))


class NoLoopCloser:
    """Loop closure off: `LoopCloser`'s calls, keeping no graph and closing no loop."""

    searches_lost_frames = False

    def restore(self, saved: LoopState | None, gaussians: int, device: torch.device) -> None:
        """Nothing to continue (loop closure's part of a checkpoint, if any, is left aside)."""

    def saved(self, keyframes: list[Keyframe]) -> None:
        """No state: a checkpoint without loop closure's part."""

    def seeded(self, count: int, keeps: bool, device: torch.device) -> None:
        """No node owns a Gaussian."""

    def kept(self, positions: torch.Tensor | None) -> None:
        """No node owns a Gaussian."""

    def close_loops(
        self, gaussians: Gaussians, keyframes: list[Keyframe], intrinsics: torch.Tensor
    ) -> tuple[Gaussians, list[Keyframe]]:
        """-> the map and the store as they are."""
        return gaussians, keyframes

    def frame_lost(
        self, gaussians: Gaussians, keyframes: list[Keyframe], lost: Keyframe, intrinsics: torch.Tensor
    ) -> tuple[Gaussians, list[Keyframe]] | None:
        """-> None: a lost frame is not searched."""
        return None

    def map_published(self, device: torch.device) -> tuple[ClosedLoop, ...]:
        """-> no loop closed."""
        return ()
