"""What a checkpoint records of the run it belongs to, so that a resume can tell it continues
the same run (the `run` entry of the checkpoint's header)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from pipeline.config import Config


@dataclass(frozen=True)
class RunDescription:
    """The source's name, whether it is live, the kind of map and, for a dataset, its layout,
    frame size and slicing. A checkpoint written by an older version may lack any of them
    (None: not recorded, so not compared)."""

    source: str | None  # the dataset's or the live source's name
    live: bool = False
    gaussians: str | None = None  # gaussians.kind
    isotropic: bool | None = None  # gaussians.isotropic
    format: str | None = None  # the dataset's layout: replica or tum
    size: tuple[int, int] | None = None  # (width, height) pixels of the frames SLAM works on
    start: int | None = None  # dataset.start
    stride: int | None = None  # dataset.stride

    @staticmethod
    def of_live(source: str, config: Config) -> RunDescription:
        return RunDescription(source, True, config.gaussians.kind, config.gaussians.isotropic)

    @staticmethod
    def of_dataset(name: str, layout: str, size: tuple[int, int], config: Config) -> RunDescription:
        gaussians, dataset = config.gaussians, config.dataset
        return RunDescription(
            name, False, gaussians.kind, gaussians.isotropic, layout, size, dataset.start, dataset.stride
        )

    def to_json(self) -> dict[str, Any]:
        """The fields recorded, as JSON values (a live run records no dataset fields)."""
        table = {item.name: getattr(self, item.name) for item in fields(self)}
        if self.size is not None:
            table["size"] = list(self.size)
        return {name: value for name, value in table.items() if value is not None}

    @staticmethod
    def from_json(table: dict[str, Any]) -> RunDescription:
        """From a checkpoint's header; keys it does not know are ignored, missing ones are None.
        TypeError or ValueError when it is not a description."""
        names = {item.name for item in fields(RunDescription)}
        known = {name: value for name, value in table.items() if name in names}
        if known.get("size") is not None:
            width, height = known["size"]
            known["size"] = (int(width), int(height))
        return RunDescription(**{"source": None, **known})
