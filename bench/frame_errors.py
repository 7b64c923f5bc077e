"""Where a run's ATE lies (#35): in a few frames tracked wrong, or in error that stretches of
frames share?

Per run folder (trajectory.txt, and groundtruth.txt or --groundtruth): each frame's camera-centre
error after the ATE's rigid alignment (`metrics.aligned_centre_errors`). A frame is an isolated
wrong frame where its error lies more than --wrong-cm from the midpoint of its two neighbours'
while those two agree within half that distance: tracked wrong, and the next frame, tracked
against the map, came back. The ATE is then given again with each such frame at that midpoint:
what a mend of isolated frames alone could gain. A step's error (`wrong_steps.py`) counts such a
frame twice, on its way out and back. The per-frame errors follow, in centimetres.
Usage: python3 bench/frame_errors.py RUN_FOLDER... [--groundtruth FILE] [--wrong-cm 3] [--out FILE.md]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pipeline.io.files.atomic import atomic_write_text
from pipeline.io.files.trajectory import read_tum_trajectory
from pipeline.metrics import aligned_centre_errors


def isolated_wrong_frames(errors: np.ndarray, wrong_m: float) -> list[int]:
    """Positions of the frames whose error [N, 3] is more than `wrong_m` from its neighbours'
    midpoint while the neighbours agree within half of that distance."""
    found = []
    for k in range(1, len(errors) - 1):
        off = float(np.linalg.norm(errors[k] - 0.5 * (errors[k - 1] + errors[k + 1])))
        if off > wrong_m and np.linalg.norm(errors[k + 1] - errors[k - 1]) < 0.5 * off:
            found.append(k)
    return found


def rms_cm(errors: np.ndarray) -> float:
    return 100 * float(np.sqrt(np.mean(np.sum(errors**2, axis=1))))


def report(folder: Path, groundtruth: Path | None, wrong_m: float) -> list[str]:
    _, estimated = read_tum_trajectory(folder / "trajectory.txt")
    own = folder / "groundtruth.txt"
    _, reference = read_tum_trajectory(own if own.exists() or groundtruth is None else groundtruth)
    errors = aligned_centre_errors(estimated, reference[: len(estimated)])
    isolated = isolated_wrong_frames(errors, wrong_m)
    mended = errors.copy()
    for k in isolated:
        mended[k] = 0.5 * (errors[k - 1] + errors[k + 1])
    per_frame = " ".join(f"{100 * e:.1f}" for e in np.linalg.norm(errors, axis=1))
    return [
        f"| {folder.name} | {rms_cm(errors):.2f} | {', '.join(map(str, isolated)) or '-'} | {rms_cm(mended):.2f} |",
        f"<!-- {folder.name} per frame (cm): {per_frame} -->",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--groundtruth", type=Path, help="reference poses (TUM format) where a folder has none")
    parser.add_argument("--wrong-cm", type=float, default=3.0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    lines = ["| run | ATE cm | isolated wrong frames | ATE without them, cm |", "|---|---|---|---|"]
    notes = []
    for folder in args.runs:
        row, per_frame = report(folder, args.groundtruth, args.wrong_cm / 100)
        lines.append(row)
        notes.append(per_frame)
    text = "\n".join(lines + [""] + notes) + "\n"
    print(text, end="")
    if args.out:
        atomic_write_text(args.out, text)


if __name__ == "__main__":
    main()
