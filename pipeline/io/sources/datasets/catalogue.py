"""The public RGB-D sequences `gsplatam download` fetches, by name: where each is published and
what of its archive it is (public.py unpacks them). Names and addresses only: the command line
reads it without loading numpy or torch."""

from __future__ import annotations

import re
from dataclasses import dataclass

from pipeline.config.choices import unknown_name
from pipeline.errors import UserError

TUM_URL = "https://cvg.cit.tum.de/rgbd/dataset/freiburg{camera}/rgbd_dataset_freiburg{camera}_{name}.tgz"
TUM_SEQUENCES = {
    1: ("xyz", "rpy", "360", "floor", "desk", "desk2", "room", "plant", "teddy"),
    2: ("xyz", "rpy", "360_hemisphere", "360_kidnap", "desk", "desk_with_person", "large_no_loop", "large_with_loop",
        "pioneer_360", "pioneer_slam", "pioneer_slam2", "pioneer_slam3", "coke", "dishes", "flowerbouquet",
        "metallic_sphere"),
    3: ("long_office_household", "nostructure_notexture_far", "nostructure_texture_far", "structure_notexture_far",
        "structure_texture_far", "structure_texture_near", "cabinet", "large_cabinet", "teddy", "sitting_static",
        "sitting_xyz", "sitting_halfsphere", "walking_static", "walking_xyz", "walking_halfsphere", "walking_rpy"),
}  # fmt: skip
REPLICA_URL = "https://cvg-data.inf.ethz.ch/nice-slam/data/Replica.zip"
REPLICA_SCENES = ("room0", "room1", "room2", "office0", "office1", "office2", "office3", "office4")
SEVEN_SCENES_URL = "https://download.microsoft.com/download/2/8/5/28564B23-0828-408F-8631-23B1EFF1DAC8/{scene}.zip"
SEVEN_SCENES = ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs")
SEVEN_SCENES_CAMERA = (585.0, 585.0, 320.0, 240.0)  # fx fy cx cy, as the dataset's page gives them
SEVEN_SCENES_FPS = 30.0
SEVEN_SCENES_NO_DEPTH = 65535
KINDS = ("tum", "replica", "7scenes")


@dataclass(frozen=True)
class Sequence:
    kind: str  # one of KINDS
    name: str  # as `gsplatam download KIND NAME` takes it
    url: str  # the publisher's archive
    member: str  # what of the archive is the sequence: a folder (tgz, Replica) or the sequence's zip (7-Scenes)
    folder: str  # the folder it is unpacked into, under the destination
    shared_archive: bool  # the archive holds other sequences too: kept after unpacking
    sha256: str = ""  # the archive's, where measured; else recorded at its first download

    @property
    def archive_name(self) -> str:
        return self.url.rsplit("/", 1)[-1]


def _tum(camera: int, name: str) -> Sequence:
    folder = f"rgbd_dataset_freiburg{camera}_{name}"
    return Sequence("tum", f"fr{camera}/{name}", TUM_URL.format(camera=camera, name=name), folder, folder, False)


def catalogue() -> dict[str, dict[str, Sequence]]:
    """kind -> name -> the sequence (7-Scenes by scene: its sequences are named seq-NN)."""
    tum = [_tum(camera, name) for camera, names in TUM_SEQUENCES.items() for name in names]
    replica = [Sequence("replica", s, REPLICA_URL, f"Replica/{s}", f"Replica/{s}", True) for s in REPLICA_SCENES]
    seven = [
        Sequence("7scenes", s, SEVEN_SCENES_URL.format(scene=s), f"{s}/seq-NN.zip", f"7scenes_{s}_seq-NN", True)
        for s in SEVEN_SCENES
    ]
    return {
        "tum": {s.name: s for s in tum},
        "replica": {s.name: s for s in replica},
        "7scenes": {s.name: s for s in seven},
    }


def sequence_of(kind: str, name: str, known: dict[str, dict[str, Sequence]] | None = None) -> Sequence:
    """The sequence `name` of `kind` (TUM: `fr1/desk`, also `freiburg1_desk` or its folder's name;
    Replica: `room0`; 7-Scenes: `chess/seq-01`); UserError with the nearest names otherwise."""
    known = known if known is not None else catalogue()
    if kind not in known:
        raise unknown_name("dataset kind", kind, known)
    names = known[kind]
    if kind == "tum":
        match = re.fullmatch(r"(?:rgbd_dataset_)?(?:freiburg|fr)([123])[_/](.+)", name)
        name = f"fr{match.group(1)}/{match.group(2)}" if match else name
    if kind == "7scenes":
        scene, _, seq = name.partition("/")
        if scene not in names or not re.fullmatch(r"seq-\d\d", seq):
            hint = "" if scene in names else f"{unknown_name('7-Scenes scene', scene, names)}; "
            raise UserError(f"{hint}name a sequence as SCENE/seq-NN, e.g. {next(iter(names))}/seq-01")
        base = names[scene]
        return Sequence(base.kind, name, base.url, f"{scene}/{seq}.zip", f"7scenes_{scene}_{seq}", True, base.sha256)
    if name not in names:
        raise unknown_name(f"{kind} sequence", name, names, listed=False)
    return names[name]
