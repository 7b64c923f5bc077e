"""Reading colour and depth images with checks that name the offending file."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from pipeline.errors import DataError
from pipeline.io.files.atomic import atomic_write_bytes


def _imread(path: Path, flags: int) -> np.ndarray:
    try:
        found = path.is_file()
    except OSError as exc:  # a folder on the way that cannot be searched (another uid's)
        raise DataError(f"cannot read the folder {path.parent} (for {path.name}): {exc.strerror}") from None
    if not found:
        raise DataError(f"missing image: {path}")
    if not os.access(path, os.R_OK):
        raise DataError(f"cannot read {path}: permission denied")
    image = cv2.imread(str(path), flags)
    if image is None:
        raise DataError(f"unreadable image: {path}")
    return image


def read_color(path: Path) -> np.ndarray:
    """-> [H, W, 3] uint8 RGB."""
    image = _imread(path, cv2.IMREAD_COLOR)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_depth_image(path: Path) -> np.ndarray:
    """A depth image as stored: [H, W] uint16 (units of the dataset's depth scale) or float32
    (metres); DataError naming it otherwise."""
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2:
        raise DataError(f"depth image {path} has {raw.shape[2]} channels, expected 1")
    if raw.dtype not in (np.uint16, np.float32):
        raise DataError(f"depth image {path} has type {raw.dtype}, expected uint16 or float32")
    return raw


def read_depth(path: Path, scale: float, shape: tuple[int, int]) -> np.ndarray:
    """Depth in metres, 0 = invalid: [H, W] float32.

    uint16 images are divided by `scale`; float32 images (e.g. TIFF) are taken as metres.
    `shape` (H, W) is the size of the matching colour image.
    """
    raw = read_depth_image(path)
    if raw.shape != shape:
        raise DataError(f"depth image {path} is {raw.shape[1]}x{raw.shape[0]}, colour is {shape[1]}x{shape[0]}")
    if raw.dtype == np.uint16:
        return raw.astype(np.float32) / np.float32(scale)
    if raw.dtype == np.float32:
        if not np.isfinite(raw).all():
            raise DataError(f"depth image {path} holds NaN or infinite values")
        if (raw < 0).any():
            raise DataError(f"depth image {path} holds negative depths")
    return raw


def resize_rgbd(
    color: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Resize colour [H, W, 3] (linear) and depth [H, W] metres (nearest: no depths mixed across
    edges) to `size` (width, height), scaling the [3, 3] intrinsics to match."""
    width, height = size
    if color.shape[:2] == (height, width):
        return color, depth, intrinsics
    scaled = intrinsics.copy()
    scaled[0] *= width / color.shape[1]
    scaled[1] *= height / color.shape[0]
    color = cv2.resize(color, (width, height), interpolation=cv2.INTER_LINEAR)
    depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
    return color, depth, scaled


def halved_to(width: int, height: int, max_width: int) -> tuple[int, int]:
    """(width, height) halved until the width is at most `max_width` (0: unchanged)."""
    while max_width and width > max_width and width % 2 == 0 and height % 2 == 0:
        width, height = width // 2, height // 2
    return width, height


def encode_depth_png(depth: np.ndarray, scale: float) -> bytes:
    """Depth [H, W] metres -> a uint16 PNG of round(depth x scale), saturating at 65535."""
    quantised = np.clip(np.rint(depth.astype(np.float64) * scale), 0, 65535).astype(np.uint16)
    return _encode(".png", quantised, [])


def encode_color(color: np.ndarray, suffix: str) -> bytes:
    """[H, W, 3] uint8 RGB -> the bytes of an image file of type `suffix` (JPEG at quality 95)."""
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if suffix.lower() in (".jpg", ".jpeg") else []
    return _encode(suffix, cv2.cvtColor(color, cv2.COLOR_RGB2BGR), params)


def _encode(suffix: str, image: np.ndarray, params: list[int]) -> bytes:
    ok, data = cv2.imencode(suffix, image, params)
    if not ok:
        raise DataError(f"cannot encode a {image.shape} {image.dtype} image as {suffix}")
    return data.tobytes()


def write_depth_png(path: Path, depth: np.ndarray, scale: float) -> None:
    """Depth [H, W] metres -> uint16 PNG of round(depth x scale), written atomically."""
    atomic_write_bytes(path, encode_depth_png(depth, scale))


def write_color(path: Path, color: np.ndarray) -> None:
    """[H, W, 3] uint8 RGB -> image file (format by extension), written atomically."""
    atomic_write_bytes(path, encode_color(color, path.suffix))
