"""Which of frames.csv's numbers tell a wrong fast step from a right one (#35)?

Per run folder (trajectory.txt, groundtruth.txt and frames.csv, as `run` writes them for a
dataset with reference poses): each frame's step error (the translation of
inv(reference step) @ estimated step, `metrics.each_step_error`) over the steps whose reference
motion is over --min-step-cm; a step is wrong where its error is over --wrong-cm. For each
numeric column: Spearman's rank correlation with the error, and the AUC of the column as a
detector of wrong steps (the chance that a wrong step's value is above a right one's: 0.5
separates nothing, 1 or 0 separates all), over all those steps and over those tracking did not
already call lost (what a new verdict would have to find). Then the wrong steps' own rows.
Usage: python3 bench/wrong_steps.py RUN_FOLDER... [--out FILE.md]
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.metrics import each_step_error

COLUMNS = ("tracking_loss", "coverage", "inlier_fraction", "residual_cm", "intensity_rms", "conditioning",
           "moved_cm", "moved_deg", "renders")  # fmt: skip


def step_table(folder: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], list[str]]:
    """-> (reference step [N-1] metres, step error [N-1] metres, column -> values [N-1] of frames
    1..N-1 (nan where empty), each frame's `lost`)."""
    _, estimated = read_tum_trajectory(folder / "trajectory.txt")
    _, reference = read_tum_trajectory(folder / "groundtruth.txt")
    lengths, errors = each_step_error(estimated, reference)
    with open(folder / "frames.csv", newline="") as table:
        rows = {int(row["index"]): row for row in csv.DictReader(table)}
    ordered = [rows[i] for i in sorted(rows)][1 : len(estimated)]
    values = {name: np.array([float(row.get(name) or "nan") for row in ordered]) for name in COLUMNS}
    return lengths, errors, values, [row["lost"] for row in ordered]


def ranks(values: np.ndarray) -> np.ndarray:
    """Ranks from 1, ties given their mean rank."""
    order = np.argsort(values, kind="stable")
    ranked = np.empty(len(values))
    ranked[order] = np.arange(1, len(values) + 1)
    for value in np.unique(values):
        tied = values == value
        ranked[tied] = ranked[tied].mean()
    return ranked


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.corrcoef(ranks(x), ranks(y))[0, 1])


def auc(values: np.ndarray, wrong: np.ndarray) -> float:
    """P(a wrong step's value > a right step's), ties counted half (Mann-Whitney)."""
    high, low = values[wrong], values[~wrong]
    if not len(high) or not len(low):
        return float("nan")
    return float(
        ((high[:, None] > low[None, :]).sum() + 0.5 * (high[:, None] == low[None, :]).sum()) / (len(high) * len(low))
    )


def report(folders: list[Path], min_step_m: float, wrong_m: float) -> str:
    lines = [f"Steps over {100 * min_step_m:g} cm; wrong: error over {100 * wrong_m:g} cm.", ""]
    lines += ["| run | steps | wrong | column | Spearman with error | AUC for wrong | not lost: steps, wrong, AUC |",
              "|---|---|---|---|---|---|---|"]  # fmt: skip
    detail = ["", "| run | frame | step cm | error cm | " + " | ".join(COLUMNS) + " | lost |",
              "|---" * (len(COLUMNS) + 5) + "|"]  # fmt: skip
    for folder in folders:
        step, error, values, lost = step_table(folder)
        large = step > min_step_m
        kept = large & ~np.array([bool(reason) for reason in lost])
        for name in COLUMNS:
            known = ~np.isnan(values[name])
            every, unflagged = large & known, kept & known
            if every.sum() < 3:
                continue
            rho = spearman(values[name][every], error[every])
            wrong, wrong_kept = error[every] > wrong_m, error[unflagged] > wrong_m
            lines.append(f"| {folder.name} | {int(every.sum())} | {int(wrong.sum())} | {name} | {rho:+.2f} "
                         f"| {auc(values[name][every], wrong):.2f} | {int(unflagged.sum())}, {int(wrong_kept.sum())}, "
                         f"{auc(values[name][unflagged], wrong_kept):.2f} |")  # fmt: skip
        for i in np.flatnonzero(large & (error > wrong_m)):
            cells = " | ".join(f"{values[name][i]:.4g}" for name in COLUMNS)
            detail.append(
                f"| {folder.name} | {i + 1} | {100 * step[i]:.1f} | {100 * error[i]:.1f} | {cells} | {lost[i]} |"
            )
    return "\n".join(lines + detail) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+")
    parser.add_argument("--min-step-cm", type=float, default=3.0)
    parser.add_argument("--wrong-cm", type=float, default=3.0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    text = report(args.folders, args.min_step_cm / 100, args.wrong_cm / 100)
    print(text, end="")
    if args.out:
        atomic_write_text(args.out, text)


if __name__ == "__main__":
    main()
