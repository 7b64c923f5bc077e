"""Record3D's Wi-Fi frame format, as pure functions.

Each video frame is depth (left half) and colour (right half), pixel-registered. Depth is the
HSV hue of the left half with saturation and value 1: depth_m = DEPTH_RANGE_M x hue, hue in
[0, 1). Invalid depth is painted red (hue 0, which also decodes near 3 m after the wrap).
Intrinsics come from `/metadata` as a column-major 3x3 at the phone's original image size.
The stream is YUV: its matrix and range decide the RGB, and so the hue and the depth.
"""

from __future__ import annotations

import math
from typing import Any

import av
import cv2
import numpy as np
from av.video.reformatter import ColorRange, Colorspace

from pipeline.config import ColorEncoding
from pipeline.errors import DataError

DEPTH_RANGE_M = 3.0  # depth = 3.0 x hue
DEPTH_VALID_M = (0.1, 2.8)  # outside [min, max) the phone's depth is not trusted
MIN_CHROMA = 0.5  # hue is meaningless where max(RGB) - min(RGB) is small (codec smear, black borders)
SEAM_MARGIN_PX = 4  # depth columns next to the colour half, mixed by the codec
EDGE_RELATIVE_JUMP = 0.05  # a 3x3 depth range above this fraction of the depth is a discontinuity
COLOR_ENCODINGS: dict[ColorEncoding, tuple[int, int]] = {  # -> (swscale matrix, AVColorRange)
    "bt709_full": (Colorspace.ITU709, ColorRange.JPEG),
    "bt601_limited": (Colorspace.ITU601, ColorRange.MPEG),
}
UNSIGNALLED_MATRICES = (0, 2, 3)  # AVColorSpace RGB, unspecified, reserved: the frame names no YUV matrix


def encode_depth(depth: np.ndarray) -> np.ndarray:
    """Depth [H, W] metres -> [H, W, 3] uint8 RGB of hue depth / 3 m; invalid depth is red."""
    valid = (depth >= DEPTH_VALID_M[0]) & (depth < DEPTH_VALID_M[1])
    hue6 = np.where(valid, depth, 0.0).astype(np.float64) * (6.0 / DEPTH_RANGE_M)
    sector = np.floor(hue6).astype(np.int64) % 6
    rise = hue6 - np.floor(hue6)
    fall = 1.0 - rise
    one, zero = np.ones_like(rise), np.zeros_like(rise)
    channels = {  # (R, G, B) per hue sector, S = V = 1
        0: (one, rise, zero),
        1: (fall, one, zero),
        2: (zero, one, rise),
        3: (zero, fall, one),
        4: (rise, zero, one),
        5: (one, zero, fall),
    }
    rgb = np.zeros(depth.shape + (3,))
    for k, (r, g, b) in channels.items():
        at = sector == k
        rgb[at] = np.stack([r[at], g[at], b[at]], axis=-1)
    return np.rint(rgb * 255.0).astype(np.uint8)


def decode_depth(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8 RGB -> depth [H, W] float32 metres, 0 where invalid.

    The hue is computed in floating point (OpenCV's 8-bit HSV would quantise it to 180 steps,
    16.7 mm). Low-chroma pixels and depths outside DEPTH_VALID_M are invalid."""
    x = rgb.astype(np.float32) * np.float32(1.0 / 255.0)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    high, low = x.max(axis=-1), x.min(axis=-1)
    chroma = high - low
    safe = np.maximum(chroma, 1e-6)
    hue6 = np.where(
        high == r,
        np.mod((g - b) / safe, 6.0),
        np.where(high == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0),
    )
    depth = hue6 * np.float32(DEPTH_RANGE_M / 6.0)
    valid = (chroma >= MIN_CHROMA) & (depth >= DEPTH_VALID_M[0]) & (depth < DEPTH_VALID_M[1])
    return np.where(valid, depth, 0.0).astype(np.float32)


def mask_unreliable_depth(depth: np.ndarray) -> np.ndarray:
    """Zero the depth columns at the seam, pixels at depth discontinuities and pixels next to
    invalid ones: the codec mixes the hues of neighbours there; -> [H, W] float32 metres, 0 = invalid."""
    out = depth.copy()
    out[:, -SEAM_MARGIN_PX:] = 0.0
    kernel = np.ones((3, 3), np.uint8)
    edge = (cv2.dilate(out, kernel) - cv2.erode(out, kernel)) > EDGE_RELATIVE_JUMP * out
    out[edge] = 0.0
    return out


def pack_frame(color: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Colour [H, W, 3] uint8 and depth [H, W] metres -> the phone's [H, 2W, 3] uint8 frame."""
    if color.shape[:2] != depth.shape:
        raise DataError(f"colour is {color.shape[1]}x{color.shape[0]}, depth {depth.shape[1]}x{depth.shape[0]}")
    return np.ascontiguousarray(np.concatenate([encode_depth(depth), color], axis=1))


def unpack_frame(packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The phone's [H, 2W, 3] uint8 frame -> colour [H, W, 3] uint8, depth [H, W] float32 metres."""
    height, width = packed.shape[:2]
    if packed.ndim != 3 or packed.shape[2] != 3:
        raise DataError(f"expected an RGB frame, got shape {packed.shape}")
    if width % 2 or width < 2 * (SEAM_MARGIN_PX + 1) or height < 3:
        raise DataError(f"frame of {width}x{height} cannot be split into depth and colour halves")
    half = width // 2
    depth = mask_unreliable_depth(decode_depth(packed[:, :half]))
    return np.ascontiguousarray(packed[:, half:]), depth


def yuv_frame(rgb: np.ndarray, encoding: ColorEncoding) -> av.VideoFrame:
    """[H, W, 3] uint8 RGB -> a yuv420p frame in `encoding`'s matrix and range (a sender's encoder input)."""
    matrix, value_range = COLOR_ENCODINGS[encoding]
    image = av.VideoFrame.from_ndarray(rgb, format="rgb24")
    return image.reformat(format="yuv420p", dst_colorspace=matrix, dst_color_range=value_range)


def rgb_array(frame: av.VideoFrame, unsignalled: ColorEncoding) -> np.ndarray:
    """A decoded frame -> [H, W, 3] uint8 RGB, by the matrix and range the frame signals, or by
    `unsignalled`'s when it names no matrix."""
    if frame.colorspace in UNSIGNALLED_MATRICES:
        matrix, value_range = COLOR_ENCODINGS[unsignalled]
    else:
        matrix, value_range = frame.colorspace, frame.color_range
    return frame.reformat(format="rgb24", src_colorspace=matrix, src_color_range=value_range).to_ndarray()


def metadata_for(intrinsics: np.ndarray, width: int, height: int) -> dict[str, Any]:
    """`/metadata` for a camera of `intrinsics` [3, 3] pixels at `width` x `height`."""
    return {"K": [float(v) for v in intrinsics.T.reshape(-1)], "originalSize": [int(width), int(height)]}


def intrinsics_from_metadata(metadata: Any, frame_height: int) -> np.ndarray:
    """`/metadata` -> [3, 3] float64 intrinsics for a frame `frame_height` pixels high.

    K is column-major at the original size; the stream's resolution adapts to bandwidth, so
    it is scaled by frame height / original height for every frame. Without `originalSize`
    the original height is taken as 256 when cy < 256, else 640 (what the app's viewer does)."""
    if not isinstance(metadata, dict) or "K" not in metadata:
        raise DataError("metadata has no 'K' (camera intrinsics)")
    values = metadata["K"]
    if not isinstance(values, list) or len(values) != 9:
        raise DataError(f"metadata 'K' must be a list of 9 numbers, got {values!r:.80}")
    try:
        numbers = [float(v) for v in values]
    except (TypeError, ValueError):
        raise DataError(f"metadata 'K' holds a non-number: {values!r:.80}") from None
    if not all(math.isfinite(v) for v in numbers):
        raise DataError("metadata 'K' holds NaN or infinite values")
    intrinsics = np.array(numbers, dtype=np.float64).reshape(3, 3).T
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    if fx <= 0 or fy <= 0 or cx <= 0 or cy <= 0:
        raise DataError(f"metadata 'K' has non-positive focal lengths or centre: fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    size = metadata.get("originalSize")
    if size is None:
        original_height = 256.0 if cy < 256 else 640.0
    elif isinstance(size, list) and len(size) == 2 and all(isinstance(v, int | float) and v > 0 for v in size):
        original_height = float(size[1])
    else:
        raise DataError(f"metadata 'originalSize' must be [width, height], got {size!r:.80}")
    scaled = intrinsics.copy()
    scaled[:2] *= frame_height / original_height
    return scaled
