"""Which global descriptor ranks loop candidates best, on generated loop sequences.

For every pair of keyframes at least 10 apart, the pair is a true revisit when, by the ground
truth, the camera centres lie within 0.5 m, the viewing directions within 60 degrees and at
least 30% of one keyframe's pixels land in the other's image (loop_candidates' gates on the
truth). Each descriptor scores every pair; reported: the ROC AUC of true against false pairs,
recall@1 (of the keyframes with a true revisit, the share whose most similar old keyframe is
one) and the time per descriptor. Keyframes: the sequence at 6 frames/s (30 frames/s with a
keyframe every 5), depth noise, holes and timestamp jitter as `synth` writes them.

    python bench/loop_descriptors.py [WIDTHxHEIGHT ...]   (default 64x48 128x96 320x240)
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import torch

from pipeline.config import DatasetConfig, SyntheticConfig
from pipeline.io.sources.datasets.loader import open_dataset
from pipeline.io.sources.datasets.synthetic import synthetic_for
from pipeline.io.sources.datasets.synthetic_writer import write_synthetic
from pipeline.slam.keyframes import overlap_fractions, sample_valid_pixels
from pipeline.slam.loops.candidates import blurred_thumbnail, descriptor, standardised

MIN_BACK, RADIUS_M, MAX_ANGLE_DEG, MIN_OVERLAP = 10, 0.5, 60.0, 0.3
VOCABULARY = 64  # ORB visual words, clustered from the sequence's own keyframes (an upper bound for ORB)


def keyframes(width: int, height: int, root: Path) -> tuple[list, torch.Tensor, torch.Tensor]:
    config = SyntheticConfig(
        loops=2, width=width, height=height, speed=1.0, fps=6.0, layout="tum", depth_noise=0.0015, holes=0.02,
        time_jitter=0.004,
    )  # fmt: skip
    path = root / f"loop_{width}x{height}"
    write_synthetic(path, synthetic_for(config, torch.device("cpu")), progress=False)
    dataset = open_dataset(DatasetConfig(path=str(path)))
    frames = list(dataset.frames())
    truth = torch.stack([torch.tensor(f.c2w_gt, dtype=torch.float32) for f in frames])
    return frames, truth, torch.tensor(dataset.intrinsics, dtype=torch.float32)


def true_pairs(frames: list, truth: torch.Tensor, intrinsics: torch.Tensor) -> np.ndarray:
    """[K, K] bool: j >= i + MIN_BACK and a true revisit (both gates on the ground truth)."""
    count = len(frames)
    generator = torch.Generator().manual_seed(0)
    labels = np.zeros((count, count), dtype=bool)
    for j in range(count):
        depth = torch.tensor(frames[j].depth)
        pixels = sample_valid_pixels(depth, 1600, generator)
        overlap = overlap_fractions(depth, intrinsics, truth[j], truth, pixels).numpy()
        distance = (truth[:, :3, 3] - truth[j, :3, 3]).norm(dim=-1).numpy()
        angle = np.degrees(np.arccos(np.clip((truth[:, :3, 2] @ truth[j, :3, 2]).numpy(), -1, 1)))
        near = (distance <= RADIUS_M) & (angle <= MAX_ANGLE_DEG) & (overlap >= MIN_OVERLAP)
        labels[j, : max(j - MIN_BACK + 1, 0)] = near[: max(j - MIN_BACK + 1, 0)]
    return labels


def inverse_depth_thumbnail(depth: torch.Tensor) -> torch.Tensor:
    """The mean inverse depth over each thumbnail cell's valid pixels, standardised."""
    inverse = torch.where(depth > 0, 1 / depth.clamp(min=1e-6), torch.zeros_like(depth))
    valid = (depth > 0).float()
    return standardised(blurred_thumbnail(inverse) / blurred_thumbnail(valid).clamp(min=1e-6))


def thumbnail_variant(use_intensity: bool, use_depth: bool) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """`descriptor` (intensity), the inverse-depth thumbnail, or both (each of norm 1/sqrt(2))."""

    def describe(color: np.ndarray, depth: np.ndarray) -> np.ndarray:
        parts = []
        if use_intensity:
            parts.append(descriptor(torch.tensor(color).float() / 255))
        if use_depth:
            parts.append(inverse_depth_thumbnail(torch.tensor(depth)))
        return (torch.cat(parts) / math.sqrt(len(parts))).numpy()

    return describe


def orb_bow(frames: list) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """ORB features (OpenCV) quantised to a vocabulary clustered from these keyframes, tf-idf, unit norm."""
    orb = cv2.ORB_create(nfeatures=500, edgeThreshold=8, patchSize=15)

    def features(color: np.ndarray) -> np.ndarray:
        _, found = orb.detectAndCompute(cv2.cvtColor(color, cv2.COLOR_RGB2GRAY), None)
        return np.zeros((0, 256), np.float32) if found is None else np.unpackbits(found, axis=1).astype(np.float32)

    every = np.concatenate([features(f.color) for f in frames])
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    words = min(VOCABULARY, max(len(every) // 4, 1))
    _, _, centres = cv2.kmeans(every, words, None, criteria, 2, cv2.KMEANS_PP_CENTERS)
    histograms = []

    def histogram(color: np.ndarray) -> np.ndarray:
        found = features(color)
        counts = np.zeros(words, np.float32)
        if len(found):
            nearest = ((found[:, None, :] - centres[None]) ** 2).sum(-1).argmin(1)
            np.add.at(counts, nearest, 1.0)
        return counts

    histograms = np.stack([histogram(f.color) for f in frames])
    idf = np.log(len(frames) / np.maximum((histograms > 0).sum(0), 1))

    def describe(color: np.ndarray, depth: np.ndarray) -> np.ndarray:
        weighted = histogram(color) * idf
        return weighted / max(float(np.linalg.norm(weighted)), 1e-12)

    return describe


def auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Probability that a true pair scores above a false one (ties count half)."""
    order = np.argsort(scores)
    ranks = np.empty(len(scores))
    ranks[order] = np.arange(1, len(scores) + 1)
    positives = labels.sum()
    negatives = len(labels) - positives
    return float((ranks[labels].sum() - positives * (positives + 1) / 2) / max(positives * negatives, 1))


def evaluate(frames: list, labels: np.ndarray, describe: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> dict:
    start = time.perf_counter()
    descriptors = np.stack([describe(f.color, f.depth) for f in frames])
    seconds = (time.perf_counter() - start) / len(frames)
    similarity = descriptors @ descriptors.T
    rows, cols = np.nonzero(np.tril(np.ones_like(labels), -MIN_BACK))
    hits = [
        bool(labels[j, int(np.argmax(similarity[j, : j - MIN_BACK + 1]))])
        for j in range(len(frames))
        if labels[j].any()
    ]
    return {
        "auc": round(auc(similarity[rows, cols], labels[rows, cols]), 3),
        "recall_at_1": round(float(np.mean(hits)), 3) if hits else math.nan,
        "ms_per_keyframe": round(1e3 * seconds, 2),
    }


def main(sizes: list[str]) -> None:
    torch.set_num_threads(1)
    results = {}
    with tempfile.TemporaryDirectory() as root:
        for size in sizes:
            width, height = (int(x) for x in size.split("x"))
            frames, truth, intrinsics = keyframes(width, height, Path(root))
            labels = true_pairs(frames, truth, intrinsics)
            variants = {
                "thumbnail intensity (descriptor)": thumbnail_variant(True, False),
                "thumbnail intensity+inverse depth": thumbnail_variant(True, True),
                "thumbnail inverse depth": thumbnail_variant(False, True),
                "ORB bag of words": orb_bow(frames),
            }
            results[size] = {
                "keyframes": len(frames),
                "true_pairs": int(labels.sum()),
                **{name: evaluate(frames, labels, describe) for name, describe in variants.items()},
            }
            print(json.dumps({size: results[size]}, indent=1), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:] or ["64x48", "128x96", "320x240"])
