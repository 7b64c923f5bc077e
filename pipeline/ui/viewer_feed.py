"""Feeding the web viewer without slowing SLAM.

At a frame boundary (the SLAM-stage observer) the map and the frame are cloned on the device,
at most `max_hz` times a second and only when the viewer thread is idle; that thread copies
them to the host on its own CUDA stream, renders depth and silhouette at the latest pose and
pushes everything to the browser. A slow or absent browser only makes snapshots rarer.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.config import Config, RenderConfig
from pipeline.frame import DeviceFrame
from pipeline.geometry import invert_pose, quat_to_rotmat
from pipeline.io.outputs.run_folder import RunFolder
from pipeline.render import Camera, Gaussians, Renderer
from pipeline.slam.gaussian_map import copied
from pipeline.slam.handoff import FrameResult
from pipeline.slam.view import SlamView
from pipeline.ui.display import FrameView, LiveFeed, MapDisplay, MapView, colorize_depth
from pipeline.ui.thumbnail import as_u8, thumbnail

log = logging.getLogger("gsplatam")

RECONNECT_GRACE_S = 5.0  # after the run, the viewer closes once nobody has watched for this long


def map_view(gaussians: Gaussians) -> MapView:
    """Activated parameters on the host: covariance R S^2 R^T, opacity sigmoid(logit)."""
    with torch.no_grad():
        rotation = quat_to_rotmat(gaussians.quats)
        covariances = (rotation * gaussians.scales().square()[:, None, :]) @ rotation.transpose(1, 2)
        return MapView(
            centers=gaussians.means.float().cpu().numpy(),
            covariances=covariances.float().cpu().numpy(),
            rgbs=gaussians.colors.clamp(0, 1).float().cpu().numpy(),
            opacities=torch.sigmoid(gaussians.opacity_logits)[:, None].float().cpu().numpy(),
        )


@dataclass
class Snapshot:
    """Device tensors cloned at a frame boundary (SLAM changes the map in place afterwards)."""

    gaussians: Gaussians
    poses: torch.Tensor  # [F, 4, 4] camera-to-world
    frame: DeviceFrame
    result: FrameResult
    fps: float
    ready: torch.cuda.Event | None  # recorded after the clones on the compute stream


def _to_u8(image: torch.Tensor) -> np.ndarray:
    return as_u8(image).cpu().numpy()


class ViewerFeed:
    """The SLAM-stage observer that feeds `viewer`; also carries out its pause and save buttons
    (pausing holds SLAM at a frame boundary; saving writes map.ply from a host copy in a thread).
    After the run it shows the final map (`finish`) and keeps it up (`linger`) until the user
    closes the page or window or presses Stop."""

    def __init__(
        self,
        viewer: MapDisplay,
        renderer: Renderer,
        render: RenderConfig,
        max_hz: float,
        folder: RunFolder,
        map_every_s: float = 0.0,
    ) -> None:
        self.viewer = viewer
        self.map_every_s = map_every_s
        self._map_sent = -float("inf")
        self.folder = folder
        self.renderer = renderer
        self.render = render
        self.period_s = 1.0 / max_hz
        self.released = threading.Event()  # set when the run stops: pausing is over
        self._saves: list[threading.Thread] = []  # "Save map now" writes, joined by close()
        self.snapshots = 0
        self._handoff: queue.Queue[Snapshot | None] = queue.Queue(maxsize=1)
        self._last = -float("inf")
        self._previous_frame_at: float | None = None
        self._fps = 0.0
        self._stream: torch.cuda.Stream | None = None
        self._latest: tuple[SlamView, DeviceFrame, FrameResult] | None = None
        self._thread = threading.Thread(target=self._work, name="viewer", daemon=True)
        self._thread.start()

    def __call__(self, slam: SlamView, frame: DeviceFrame, result: FrameResult) -> None:
        now = time.perf_counter()
        if self._previous_frame_at is not None:
            self._fps = 1.0 / max(now - self._previous_frame_at, 1e-9)
        self._previous_frame_at = now
        self._latest = (slam, frame, result)
        while not self.viewer.running.wait(0.2) and not self.released.is_set():
            pass  # paused from the browser
        if self.viewer.save_requested.is_set() and slam.gaussians is not None:
            self.viewer.save_requested.clear()
            host = copied(slam.gaussians, "cpu")
            save = threading.Thread(target=self._save, args=(host,), name="viewer-save")
            save.start()
            self._saves = [t for t in self._saves if t.is_alive()] + [save]
        if now - self._last < self.period_s or self._handoff.full() or slam.gaussians is None:
            return
        if not self.viewer.clients():
            return  # nobody is watching: no snapshot
        self._last = now
        self._handoff.put_nowait(self._snapshot(slam, frame, result))

    def _snapshot(self, slam: SlamView, frame: DeviceFrame, result: FrameResult) -> Snapshot:
        """Clones of the map and poses on the device (then SLAM may go on)."""
        assert slam.gaussians is not None
        cuda = frame.depth.is_cuda
        snapshot = Snapshot(
            gaussians=copied(slam.gaussians),
            poses=torch.stack(slam.poses),
            frame=frame,
            result=result,
            fps=self._fps,
            ready=torch.cuda.Event() if cuda else None,
        )
        if snapshot.ready is not None:
            snapshot.ready.record()
            if self._stream is None:
                self._stream = torch.cuda.Stream(frame.depth.device)
        self.snapshots += 1
        return snapshot

    def finish(self) -> None:
        """SLAM has stopped: show its final state, map included (the last frames may not have been
        shown), and let a paused SLAM go."""
        self.released.set()
        if self._latest is None or self._latest[0].gaussians is None:
            return
        self._map_sent = -float("inf")
        with contextlib.suppress(queue.Empty):
            self._handoff.get_nowait()  # an older snapshot not yet shown
        self._handoff.put(self._snapshot(*self._latest))

    def linger(self, summary: str) -> None:
        """Show `summary` and wait while someone watches, until Stop, the page or window closed
        (for RECONNECT_GRACE_S, so a reload does not end it) or Ctrl-C."""
        self.viewer.show_summary(summary)
        if self.viewer.stopped.is_set() or not self.viewer.clients():
            return
        log.info("viewer: the run is over; the final map stays up until the page is closed or Stop is pressed")
        unwatched_since: float | None = None
        try:
            while not self.viewer.stopped.wait(0.5):
                if self.viewer.clients():
                    unwatched_since = None
                elif unwatched_since is None:
                    unwatched_since = time.monotonic()
                elif time.monotonic() - unwatched_since >= RECONNECT_GRACE_S:
                    return
        except KeyboardInterrupt:
            return

    def _save(self, gaussians: Gaussians) -> None:
        try:
            self.folder.write_map(gaussians)
        except OSError as exc:
            log.error("viewer: saving %s failed: %s", self.folder.map, exc)
            self.viewer.show_saved(f"saving {self.folder.map} failed: {exc}")
            return
        message = f"saved {len(gaussians):,} Gaussians to {self.folder.map} at {time.strftime('%H:%M:%S')}"
        log.info("viewer: %s", message)
        self.viewer.show_saved(message)

    def _work(self) -> None:
        while (snapshot := self._handoff.get()) is not None:
            try:
                self._show(snapshot)
            except Exception:  # the viewer must never stop SLAM
                log.exception("viewer: update failed")

    def _show(self, snap: Snapshot) -> None:
        stream = torch.cuda.stream(self._stream) if self._stream is not None else contextlib.nullcontext()
        with stream, torch.no_grad():
            if snap.ready is not None:
                torch.cuda.current_stream().wait_event(snap.ready)
            cfg = self.render
            small = thumbnail(snap.frame)  # the panel shows thumbnails: render and send them
            camera = Camera(invert_pose(snap.poses[-1]), small.intrinsics, small.width, small.height, cfg.near, cfg.far)
            out = self.renderer(snap.gaussians, camera)
            far = float(small.depth.max()) or 1.0
            view = FrameView(
                index=snap.frame.index,
                poses=snap.poses.double().cpu().numpy(),
                intrinsics=small.intrinsics.double().cpu().numpy(),
                color=small.color.cpu().numpy(),
                depth=colorize_depth(small.depth.cpu().numpy(), far),
                rendered_depth=colorize_depth(out.depth.cpu().numpy(), far),
                silhouette=np.repeat(_to_u8(out.silhouette)[..., None], 3, axis=-1),
                stats=self._stats(snap),
            )
            splats = None
            if time.monotonic() - self._map_sent >= self.map_every_s:
                splats = map_view(snap.gaussians)  # the costly part: a host copy, packing and sending
                self._map_sent = time.monotonic()
        if splats is not None:
            self.viewer.show_map(splats)
        self.viewer.show_frame(view)

    def _stats(self, snap: Snapshot) -> str:
        r = snap.result
        ms = {k: 1000 * v for k, v in r.seconds.items()}
        tracking = f"lost ({r.lost})" if r.lost else "ok"
        return (
            f"**frame {r.index}** &nbsp; {snap.fps:.1f} fps &nbsp; {r.gaussians:,} Gaussians\n\n"
            f"tracking {ms['tracking']:.0f} ms, densify {ms['densify']:.0f} ms, mapping {ms['mapping']:.0f} ms "
            f"(total {ms['total']:.0f} ms)\n\ntracking: {tracking}"
        )

    def close(self) -> None:
        """Stop the viewer thread after the update in progress, let requested saves finish and
        confirm in the page, then close the viewer; safe twice."""
        if not self._thread.is_alive():
            return
        self.released.set()
        with contextlib.suppress(queue.Empty):
            self._handoff.get_nowait()  # a snapshot not yet shown is dropped
        self._handoff.put(None)
        self._thread.join(timeout=30)
        for save in self._saves:
            save.join()  # a map the user asked for is never lost to the shutdown
        self.viewer.close()


def attach_viewer(
    config: Config, renderer: Renderer, device: torch.device, folder: RunFolder, title: str
) -> LiveFeed | None:
    """Start the viewer of `config.viewer.kind` when `config.viewer.enabled`; -> the observer to
    give the SLAM stage."""
    if not config.viewer.enabled:
        return None
    v = config.viewer
    if v.kind == "rerun":
        from pipeline.ui.rerun_feed import attach_rerun

        return attach_rerun(v, device, folder.path.name)
    viewer: MapDisplay
    if v.kind == "open3d":
        from pipeline.ui.open3d_viewer import Open3DViewer

        viewer = Open3DViewer(title)
    else:
        from pipeline.ui.viewer import Viewer

        viewer = Viewer(v.host, v.port, title)
    return ViewerFeed(viewer, renderer, config.render, v.max_hz, folder, v.map_every_s)


async def release_on_stop(feed: LiveFeed, stop: asyncio.Event) -> None:
    """A runtime service: once the run is asked to stop, a paused SLAM may go on to finish."""
    await stop.wait()
    feed.released.set()
