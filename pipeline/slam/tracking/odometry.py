"""Visual odometry from image features: how the camera moved between two frames.

Dense alignment against the rendered map converges from a guess within a few centimetres of the
truth; constant velocity gives such a guess only while the motion is smooth and slow. Features
matched between two frames do not care how far the camera moved, as long as the views overlap:
ORB keypoints of the earlier frame, lifted by its depth, are matched to the later frame's and the
later camera's pose is solved from them (PnP in RANSAC, two solvers, refined by
Levenberg-Marquardt). A solve is kept only when enough matches agree with it in 3D as well, with
the later frame's own depth: on a weakly textured view PnP can return a pose that fits a few
matches in the image and none in depth. Plain NumPy and OpenCV on the host; the pipeline runs it beside the GPU
(`pipeline/stages/odometry.py`).
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.frame import FrameMotion, ImageFeatures

# Lowe's ratio test: a match is kept when its distance is below this fraction of the second
# best's; the looser only where the stricter leaves too few matches agreeing with a motion
# (on the cabinet's 56 fast real steps at 640x480: 9 steps found no motion at 0.8, 4 with 0.9
# after it, the 5 filled within 1.0-2.6 cm of the reference; bench/NOTES.md, Change 31).
RATIO_TESTS = (0.8, 0.9)
REPROJECTION_PX = 3.0  # RANSAC's inlier threshold at 640 pixels of width (scaled with the image)
# PnP solvers tried, each with its most RANSAC iterations (it stops once 99.9% sure); the pose more
# matches agree with in depth is kept. AP3P's four-point samples are clean far more often at the
# 30% of correct matches a fast step leaves (hundreds of iterations); EPnP's five points are
# better conditioned on a plane seen head-on, where AP3P trades a sideways step for a turn.
PNP_SOLVERS = ((cv2.SOLVEPNP_AP3P, 1000), (cv2.SOLVEPNP_EPNP, 100))
AGREE_M = 0.03  # a PnP inlier agrees in 3D when it lands within this ...
AGREE_FRACTION = 0.03  # ... plus this fraction of its depth of the later frame's own point
FAST_THRESHOLD = 5  # low: real indoor images are smooth (a plain cabinet gives 190 keypoints at 20)
BORDER_PX = 15  # ORB's edge threshold and patch size


def detector(max_features: int) -> cv2.ORB:
    """An ORB detector; one per thread (OpenCV's detectors are not shared across threads)."""
    return cv2.ORB.create(max_features, fastThreshold=FAST_THRESHOLD, edgeThreshold=BORDER_PX, patchSize=BORDER_PX)


def extract_features(orb: cv2.ORB, color: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray) -> ImageFeatures:
    """The ORB keypoints of `color` [H, W, 3] uint8 RGB, each lifted by `depth` [H, W] (metres,
    0 = none) through `intrinsics` [3, 3] (pixels) into the camera's frame."""
    gray = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY)
    keypoints, descriptors = orb.detectAndCompute(gray, None)
    pixels = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2)
    if descriptors is None:
        descriptors = np.zeros((0, 32), dtype=np.uint8)
    rows = np.clip(np.rint(pixels[:, 1]).astype(np.int64), 0, depth.shape[0] - 1)
    cols = np.clip(np.rint(pixels[:, 0]).astype(np.int64), 0, depth.shape[1] - 1)
    z = depth[rows, cols].astype(np.float32)
    x = (pixels[:, 0] - intrinsics[0, 2]) / intrinsics[0, 0] * z
    y = (pixels[:, 1] - intrinsics[1, 2]) / intrinsics[1, 1] * z
    return ImageFeatures(pixels, descriptors, np.stack([x, y, z], axis=1).astype(np.float32))


def match(earlier: ImageFeatures, later: ImageFeatures) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each earlier keypoint with depth and its best match among the later ones: indices into
    `earlier`, into `later`, and the ratio of the best match's distance to the second best's
    (Lowe's test keeps the low ones); three [M] arrays."""
    none = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0))
    if len(earlier.descriptors) < 2 or len(later.descriptors) < 2:
        return none
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(earlier.descriptors, later.descriptors, k=2)
    best = [(a.queryIdx, a.trainIdx, _ratio(a.distance, b.distance)) for a, b in (p for p in pairs if len(p) == 2)]
    if not best:
        return none
    found = np.array(best)
    first, second = found[:, 0].astype(np.int64), found[:, 1].astype(np.int64)
    with_depth = earlier.points[first, 2] > 0
    return first[with_depth], second[with_depth], found[with_depth, 2]


def _ratio(best: float, second: float) -> float:
    """Lowe's ratio; 1 (never kept) where both distances are 0: two keypoints match equally."""
    return best / second if second > 0 else 1.0


def relative_motion(
    earlier: ImageFeatures, later: ImageFeatures, intrinsics: np.ndarray, width: int, min_inliers: int, since: int
) -> FrameMotion | None:
    """The later camera's pose in the earlier camera's frame, from features matched between the
    two frames (`intrinsics` [3, 3] pixels, the images `width` pixels wide; `since` the earlier
    frame's index), under the strictest ratio test of `RATIO_TESTS` that yields one; None when
    under each fewer than `min_inliers` matches agree with it in the image and in depth."""
    first, second, ratio = match(earlier, later)
    tried = -1
    for limit in RATIO_TESTS:
        kept = ratio < limit
        if int(kept.sum()) == tried:  # no match more than under the stricter test: the same solve again
            continue
        tried = int(kept.sum())
        motion = _motion(earlier.points[first[kept]], later.pixels[second[kept]], later.points[second[kept]],
                         intrinsics, width, min_inliers)  # fmt: skip
        if motion is not None:
            return FrameMotion(since, np.linalg.inv(motion[0]), motion[1])
    return None


def _motion(
    world: np.ndarray, image: np.ndarray, seen: np.ndarray, intrinsics: np.ndarray, width: int, min_inliers: int
) -> tuple[np.ndarray, int] | None:
    """The best of `PNP_SOLVERS` for matched earlier points `world` [M, 3] seen at later pixels
    `image` [M, 2] (and as later points `seen` [M, 3]) -> (later camera from earlier camera
    [4, 4], inliers agreeing in depth); None when fewer than `min_inliers` agree."""
    if len(world) < max(min_inliers, 6):
        return None
    world, image, seen = world.astype(np.float64), image.astype(np.float64), seen.astype(np.float64)
    solves = [_solve(world, image, seen, intrinsics, width, solver, min_inliers) for solver in PNP_SOLVERS]
    best = max((solve for solve in solves if solve is not None), key=lambda solve: solve[1], default=None)
    if best is None or best[1] < min_inliers:
        return None
    return best


def _solve(
    world: np.ndarray,
    image: np.ndarray,
    seen: np.ndarray,
    intrinsics: np.ndarray,
    width: int,
    solver: tuple[int, int],
    min_inliers: int,
) -> tuple[np.ndarray, int] | None:
    """One PnP in RANSAC (`solver`: OpenCV's flag, the most iterations) of the matched earlier
    points `world` [M, 3] onto the later pixels `image` [M, 2], refined on its inliers ->
    (later camera from earlier camera [4, 4], how many inliers agree with the later frame's own
    points `seen` [M, 3]); None when RANSAC keeps fewer than `min_inliers`."""
    k = intrinsics.astype(np.float64)
    flags, iterations = solver
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        world, image, k, None, iterationsCount=iterations,
        reprojectionError=REPROJECTION_PX * width / 640, confidence=0.999, flags=flags,
    )  # fmt: skip
    if not found or inliers is None or len(inliers) < min_inliers:
        return None
    kept = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(world[kept], image[kept], k, None, rvec, tvec)
    later_from_earlier = np.eye(4)
    later_from_earlier[:3, :3] = cv2.Rodrigues(rvec)[0]
    later_from_earlier[:3, 3] = tvec[:, 0]
    moved = world[kept] @ later_from_earlier[:3, :3].T + later_from_earlier[:3, 3]
    target = seen[kept]
    agree = (target[:, 2] > 0) & (np.linalg.norm(moved - target, axis=1) < AGREE_M + AGREE_FRACTION * target[:, 2])
    return later_from_earlier, int(agree.sum())
