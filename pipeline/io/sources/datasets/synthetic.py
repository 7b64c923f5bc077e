"""A procedural textured room rendered exactly by ray casting: colour, depth and poses.

World frame: z up, metres. Cameras use OpenCV axes (x right, y down, z forward) and the
pixel-centre convention of the renderer: the ray of pixel (u, v) passes through
((u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy, 1) in camera coordinates.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, fields, replace

import numpy as np
import torch

from pipeline.config import SYNTHETIC_CPU, SYNTHETIC_GPU, SyntheticConfig
from pipeline.config.loading import MAX_SYNTHETIC_FRAMES
from pipeline.errors import UserError

ROOM_HALF = (3.0, 2.5)  # room half-extent in x and y
ROOM_HEIGHT = 2.6
PATH_CENTRE = (0.0, 0.0, 1.4)
LOOP_HALF_AXES = (1.0, 0.8)  # metres: the closed path's ellipse in x and y (the open path's reach)
LOOP_LOOK_AHEAD = 0.6  # radians: the closed path's camera looks outward, turned this much along the path
TRAP_TURNS = 0.7  # a trap sequence without loops goes this far round: its last 0.2 turn repeats its first, turned
NO_HIT = 1e9
CPU = torch.device("cpu")


@dataclass(frozen=True)
class Scene:
    """Primitives with per-object texture parameters (object 0 is the room itself)."""

    boxes: torch.Tensor  # [B, 6] (min xyz, max xyz)
    spheres: torch.Tensor  # [S, 4] (centre xyz, radius)
    cylinders: torch.Tensor  # [Y, 5] (centre x, y, z bottom, z top, radius), axis vertical
    colors: torch.Tensor  # [K, 2, 3] two colours per object in [0, 1]
    checker: torch.Tensor  # [K] checker cell size, metres
    stripe_dir: torch.Tensor  # [K, 3] stripe wave vector, radians per metre
    turned: torch.Tensor | None = None  # [K] bool in a symmetric room: the object is the twin of another

    def to(self, device: torch.device) -> Scene:
        tensors = {f.name: getattr(self, f.name).to(device) for f in fields(self) if f.name != "turned"}
        return Scene(**tensors, turned=None if self.turned is None else self.turned.to(device))


def _place_objects(rng: np.random.Generator) -> list[tuple[str, list[float]]]:
    """Twelve (kind, parameters) along the walls, by angle round the room, in that order."""
    placed: list[tuple[str, list[float]]] = []
    kinds = ["box", "sphere", "cylinder"] * 4
    angles = np.linspace(0, 2 * math.pi, len(kinds), endpoint=False) + rng.uniform(0, 0.3)
    for kind, angle in zip(kinds, angles):
        size = rng.uniform(0.2, 0.45)
        reach = rng.uniform(1.9, 2.3)
        x = float(np.clip(reach * math.cos(angle), -ROOM_HALF[0] + size, ROOM_HALF[0] - size))
        y = float(np.clip(reach * math.sin(angle), -ROOM_HALF[1] + size, ROOM_HALF[1] - size))
        if kind == "box":
            z0 = rng.choice([0.0, rng.uniform(0.5, 1.4)])
            half = np.array([size, rng.uniform(0.15, 0.4), rng.uniform(0.2, 0.6)])
            placed.append((kind, [x - half[0], y - half[1], z0, x + half[0], y + half[1], z0 + 2 * half[2]]))
        elif kind == "sphere":
            placed.append((kind, [x, y, rng.uniform(0.4, 1.8), size]))
        else:
            placed.append((kind, [x, y, 0.0, rng.uniform(0.6, 1.8), size * 0.7]))
    return placed


def _turned_object(kind: str, params: list[float]) -> list[float]:
    """An object's parameters turned by 180 degrees about the vertical axis through the room's centre."""
    if kind == "box":
        x0, y0, z0, x1, y1, z1 = params
        return [-x1, -y1, z0, -x0, -y0, z1]
    return [-params[0], -params[1], *params[2:]]


def make_scene(seed: int, symmetric: bool = False) -> Scene:
    """A room with boxes, spheres and cylinders along its walls, all high-frequency textured.

    `symmetric`: the objects of the room's second half (by angle) are those of the first turned
    by 180 degrees about the vertical axis through the centre, textured alike, and so are the
    walls, floor and ceiling (y < 0 is textured as the turned y > 0): every view of one half has
    a twin in the other, from the turned pose, that looks the same but is elsewhere."""
    rng = np.random.default_rng(seed)
    placed = _place_objects(rng)
    twin_of = list(range(len(placed)))  # the object whose textures each one takes
    if symmetric:
        half = len(placed) // 2
        placed = placed[:half] + [(kind, _turned_object(kind, params)) for kind, params in placed[:half]]
        twin_of = list(range(half)) * 2
    order = [k for kind in ("box", "sphere", "cylinder") for k, (other, _) in enumerate(placed) if other == kind]
    boxes, spheres, cylinders = (
        [placed[k][1] for k in order if placed[k][0] == kind] for kind in ("box", "sphere", "cylinder")
    )
    objects = 1 + len(placed)
    direction = rng.normal(size=(objects, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    wavelength = rng.uniform(0.08, 0.2, size=(objects, 1))

    def tensor(values: object) -> torch.Tensor:
        return torch.tensor(np.asarray(values), dtype=torch.float32)

    identity = {k: 1 + position for position, k in enumerate(order)}  # placement -> object id
    texture = torch.tensor([0] + [identity[twin_of[k]] for k in order])  # object id -> the id whose texture it has
    scene = Scene(
        boxes=tensor(boxes).reshape(-1, 6),
        spheres=tensor(spheres).reshape(-1, 4),
        cylinders=tensor(cylinders).reshape(-1, 5),
        colors=tensor(rng.uniform(0.05, 0.95, size=(objects, 2, 3)))[texture],
        checker=tensor(rng.uniform(0.1, 0.3, size=objects))[texture],
        stripe_dir=tensor(direction * 2 * math.pi / wavelength)[texture],
    )
    if symmetric:
        scene = replace(scene, turned=torch.tensor([False] + [k >= len(placed) // 2 for k in order]))
    return scene


def look_at(position: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Camera-to-world [4, 4] at `position` looking along `forward`, world z up."""
    f = forward / np.linalg.norm(forward)
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, f], axis=1)
    pose[:3, 3] = position
    return pose


def _shake(t: np.ndarray, phase: np.ndarray) -> list[np.ndarray]:
    """Hand-held shake in x, y and z at times `t` (seconds): three sines each, in [-1, 1]."""
    return [
        sum(np.sin(2 * math.pi * f * t + phase[3 + 3 * k + j]) for j, f in enumerate((1.3, 2.9, 4.7))) / 3
        for k in range(3)
    ]


def loop_length() -> float:
    """Metres round the closed path's ellipse (Ramanujan's approximation)."""
    a, b = LOOP_HALF_AXES
    return math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))


def path_turns(config: SyntheticConfig) -> float:
    """How many times a sequence goes round the closed path: `loops`, else TRAP_TURNS for a
    trap, else 0 (the open path)."""
    return float(config.loops) if config.loops else TRAP_TURNS if config.trap else 0.0


def closed_path_frames(config: SyntheticConfig) -> int:
    """The frames of the whole closed path at `speed` and `fps`, the last back at the start."""
    return round(path_turns(config) * loop_length() / config.speed * config.fps) + 1


def trajectory(config: SyntheticConfig, frames: int) -> np.ndarray:
    """A smooth hand-held-like path around the room centre: [frames, 4, 4] camera-to-world.
    With `loops` (or `trap`), the closed path of `closed_path`, else an open one."""
    rng = np.random.default_rng(config.seed + 1)
    phase = rng.uniform(0, 2 * math.pi, size=12)
    t = np.arange(frames) / config.fps
    if path_turns(config):
        return closed_path(config, t, phase)
    omega = config.speed / 0.9  # the path below moves about 0.9 m per radian
    centre = np.asarray(PATH_CENTRE)
    shake = _shake(t, phase)
    position = np.stack(
        [
            centre[0] + 1.0 * np.sin(0.7 * omega * t + phase[0]) + config.jitter * shake[0],
            centre[1] + 0.8 * np.sin(omega * t + phase[1]) + config.jitter * shake[1],
            centre[2] + 0.15 * np.sin(0.5 * omega * t + phase[2]) + config.jitter * shake[2],
        ],
        axis=1,
    )
    yaw = phase[0] + 0.4 * omega * t + 0.5 * config.jitter * shake[0]
    pitch = -0.15 + 0.1 * np.sin(0.3 * omega * t) + 0.5 * config.jitter * shake[1]
    forward = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    return np.stack([look_at(p, f) for p, f in zip(position, forward)])


def closed_path(config: SyntheticConfig, t: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """An ellipse round the room's centre at `speed` (on average), looking outward and a little
    ahead, with the open path's shake: at times `t` [F] seconds -> [F, 4, 4] camera-to-world.
    It comes back to its start (within the shake) every turn, and the pose half a turn on is
    the start's turned by 180 degrees about the vertical axis through the centre (height and
    pitch repeat every half turn), so in a symmetric room it sees the twin of the same view."""
    angle = 2 * math.pi * config.speed / loop_length() * t + phase[0]
    shake = _shake(t, phase)
    (a, b), centre = LOOP_HALF_AXES, np.asarray(PATH_CENTRE)
    position = np.stack(
        [
            centre[0] + a * np.cos(angle) + config.jitter * shake[0],
            centre[1] + b * np.sin(angle) + config.jitter * shake[1],
            centre[2] + 0.15 * np.sin(2 * angle) + config.jitter * shake[2],
        ],
        axis=1,
    )
    yaw = angle + LOOP_LOOK_AHEAD + 0.5 * config.jitter * shake[0]
    pitch = -0.15 + 0.1 * np.sin(2 * angle) + 0.5 * config.jitter * shake[1]
    forward = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    return np.stack([look_at(p, f) for p, f in zip(position, forward)])


def default_intrinsics(width: int, height: int) -> np.ndarray:
    """Replica's 90-degree horizontal field of view at any size, square pixels."""
    focal = 600.0 * width / 1200.0
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def _slab(origin: torch.Tensor, dirs: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, inside: bool) -> torch.Tensor:
    """Ray-box distances [R]: the exit face for the room (`inside`), else the entry face."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t1, t2 = (lo - origin) * inv, (hi - origin) * inv
    far = torch.maximum(t1, t2).amin(dim=1)
    if inside:
        return far
    near = torch.minimum(t1, t2).amax(dim=1)
    return torch.where(near <= far, near, NO_HIT)


def _box_normal(point: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Outward normals [M, 3] of points on a box's faces: the axis where the point is most extreme."""
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    rel = (point - centre) / half
    axis = rel.abs().argmax(dim=1, keepdim=True)
    return torch.zeros_like(point).scatter_(1, axis, torch.sign(rel.gather(1, axis)))


def _object_bounds(scene: Scene) -> list[tuple[str, torch.Tensor, torch.Tensor]]:
    """(kind, parameters, axis-aligned bounds [2, 3]) for every object, in object-id order from 1."""
    objects = [("box", b, b.reshape(2, 3)) for b in scene.boxes]
    objects += [("sphere", s, torch.stack([s[:3] - s[3], s[:3] + s[3]])) for s in scene.spheres]
    objects += [
        (
            "cylinder",
            c,
            torch.stack([torch.stack([c[0] - c[4], c[1] - c[4], c[2]]), torch.stack([c[0] + c[4], c[1] + c[4], c[3]])]),
        )
        for c in scene.cylinders
    ]
    return objects


def distance_to_surfaces(scene: Scene, points: torch.Tensor) -> torch.Tensor:
    """Unsigned distance [N] (metres) from world points [N, 3] to the nearest surface of the
    room: its walls, floor and ceiling, and every box, sphere and capped cylinder."""
    lo = torch.tensor([-ROOM_HALF[0], -ROOM_HALF[1], 0.0])
    hi = torch.tensor([ROOM_HALF[0], ROOM_HALF[1], ROOM_HEIGHT])
    best = _box_distance(points, lo, hi)
    for box in scene.boxes:
        best = torch.minimum(best, _box_distance(points, box[:3], box[3:]))
    for sphere in scene.spheres:
        best = torch.minimum(best, ((points - sphere[:3]).norm(dim=1) - sphere[3]).abs())
    for c in scene.cylinders:
        radial = (points[:, :2] - c[:2]).norm(dim=1) - c[4]
        axial = torch.maximum(c[2] - points[:, 2], points[:, 2] - c[3])
        outside = torch.stack([radial, axial], dim=1).clamp(min=0).norm(dim=1)
        best = torch.minimum(best, outside + torch.maximum(radial, axial).clamp(max=0).abs())
    return best


def _box_distance(points: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Unsigned distance [N] from points [N, 3] to the faces of the box [lo, hi]."""
    q = (points - (lo + hi) / 2).abs() - (hi - lo) / 2
    return q.clamp(min=0).norm(dim=1) + q.amax(dim=1).clamp(max=0).abs()


def _screen_rect(
    bounds: torch.Tensor, w2c: torch.Tensor, intrinsics: np.ndarray, width: int, height: int
) -> tuple[int, int, int, int]:
    """Pixel rectangle (v0, v1, u0, u1) that holds every ray able to hit the box `bounds` [2, 3]."""
    corners = torch.cartesian_prod(bounds[:, 0], bounds[:, 1], bounds[:, 2])
    cam = corners @ w2c[:3, :3].T + w2c[:3, 3]
    if (cam[:, 2] <= 0.05).any():
        return 0, height, 0, width
    u = intrinsics[0, 0] * cam[:, 0] / cam[:, 2] + intrinsics[0, 2]
    v = intrinsics[1, 1] * cam[:, 1] / cam[:, 2] + intrinsics[1, 2]
    u0, u1 = max(0, int(u.min()) - 2), min(width, int(u.max()) + 2)
    v0, v1 = max(0, int(v.min()) - 2), min(height, int(v.max()) + 2)
    return (v0, v1, u0, u1) if u0 < u1 and v0 < v1 else (0, 0, 0, 0)


def cast(
    scene: Scene, origin: torch.Tensor, dirs: torch.Tensor, rects: list[tuple[int, int, int, int]]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays (origin [3], directions [H, W, 3] with camera-z component 1) -> (z-depth [H, W], colour [H, W, 3]).

    Object k (from 1) is tested only inside its screen rectangle rects[k - 1]; the nearest hit
    per ray is found first and normals are computed only for the winners.
    """
    height, width = dirs.shape[:2]
    device = dirs.device
    room_lo = torch.tensor([-ROOM_HALF[0], -ROOM_HALF[1], 0.0], device=device)
    room_hi = torch.tensor([ROOM_HALF[0], ROOM_HALF[1], ROOM_HEIGHT], device=device)
    best_t = _slab(origin, dirs.reshape(-1, 3), room_lo, room_hi, inside=True).reshape(height, width)
    best_id = torch.zeros(height, width, dtype=torch.long, device=device)
    objects = _object_bounds(scene)
    for obj, ((kind, params, _), (v0, v1, u0, u1)) in enumerate(zip(objects, rects), start=1):
        if v0 == v1:
            continue
        d = dirs[v0:v1, u0:u1].reshape(-1, 3)
        if kind == "box":
            t = _slab(origin, d, params[:3], params[3:], inside=False)
        elif kind == "sphere":
            oc = origin - params[:3]
            a, b = (d * d).sum(1), d @ oc
            disc = b * b - a * (oc @ oc - params[3] ** 2)
            t = torch.where(disc >= 0, (-b - disc.clamp(min=0).sqrt()) / a, NO_HIT)
        else:
            dxy, oxy = d[:, :2], origin[:2] - params[:2]
            a2 = (dxy * dxy).sum(1).clamp(min=1e-12)
            b2 = dxy @ oxy
            disc = b2 * b2 - a2 * (oxy @ oxy - params[4] ** 2)
            t = torch.where(disc >= 0, (-b2 - disc.clamp(min=0).sqrt()) / a2, NO_HIT)
            z = origin[2] + t * d[:, 2]
            t = torch.where((z >= params[2]) & (z <= params[3]), t, NO_HIT)
            dz = torch.where(d[:, 2].abs() < 1e-12, 1e-12, d[:, 2])
            t_cap = (params[3] - origin[2]) / dz
            cap_xy = oxy + t_cap[:, None] * dxy
            t_cap = torch.where((cap_xy * cap_xy).sum(1) <= params[4] ** 2, t_cap, NO_HIT)
            t = torch.where((t_cap > 1e-4) & (t_cap < t), t_cap, t)
        t = t.reshape(v1 - v0, u1 - u0)
        region_t, region_id = best_t[v0:v1, u0:u1], best_id[v0:v1, u0:u1]
        hit = (t > 1e-4) & (t < region_t)
        region_t.copy_(torch.where(hit, t, region_t))
        region_id.masked_fill_(hit, obj)

    flat_id = best_id.reshape(-1)
    point = origin + best_t.reshape(-1, 1) * dirs.reshape(-1, 3)
    normal = -_box_normal(point, room_lo, room_hi)
    for obj, (kind, params, _) in enumerate(objects, start=1):
        mask = flat_id == obj
        p = point[mask]
        if kind == "box":
            normal[mask] = _box_normal(p, params[:3], params[3:])
        elif kind == "sphere":
            normal[mask] = (p - params[:3]) / params[3]
        else:
            radial = torch.cat([(p[:, :2] - params[:2]) / params[4], torch.zeros_like(p[:, :1])], dim=1)
            on_cap = (p[:, 2:] - params[3]).abs() < 1e-4
            normal[mask] = torch.where(on_cap, torch.tensor([0.0, 0.0, 1.0], device=device), radial)
    if scene.turned is not None:
        point, normal = _turned_back(scene.turned, point, normal, flat_id)
    return best_t, shade(scene, point, normal, flat_id).reshape(height, width, 3)


def _turned_back(
    turned: torch.Tensor, point: torch.Tensor, normal: torch.Tensor, ids: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """In a symmetric room, the points [M, 3] and normals [M, 3] of the twin objects and of the
    room's half y < 0, turned back by 180 degrees about the vertical axis through the centre, so
    they are textured and lit as their originals."""
    back = (turned[ids] | ((ids == 0) & (point[:, 1] < 0)))[:, None]
    flip = torch.tensor([-1.0, -1.0, 1.0], device=point.device)
    return torch.where(back, point * flip, point), torch.where(back, normal * flip, normal)


def shade(scene: Scene, point: torch.Tensor, normal: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """View-independent colour: a checker and stripe texture under fixed diffuse light."""
    cell = scene.checker[ids][:, None]
    checker = torch.floor(point / cell).sum(1).remainder(2.0)
    stripes = 0.5 + 0.5 * torch.sin((point * scene.stripe_dir[ids]).sum(1))
    mix = (0.55 * checker + 0.45 * stripes)[:, None]
    pair = scene.colors[ids]
    albedo = pair[:, 0] * mix + pair[:, 1] * (1 - mix)
    light = torch.tensor([0.4, 0.3, 0.87], device=point.device)
    diffuse = (normal * light).sum(1).abs()[:, None]
    return albedo * (0.5 + 0.5 * diffuse)


def render_view(
    scene: Scene, c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int, supersample: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """-> (colour [H, W, 3] uint8, depth [H, W] float32 metres) seen by camera-to-world `c2w`.

    Rays are cast on the scene's device. Colour averages `supersample` x `supersample` rays per
    pixel; depth is the pixel centre's.
    """
    device = scene.colors.device
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    rotation = torch.tensor(c2w[:3, :3], dtype=torch.float32, device=device)
    origin = torch.tensor(c2w[:3, 3], dtype=torch.float32, device=device)
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float32, device=device),
        torch.arange(width, dtype=torch.float32, device=device),
        indexing="ij",
    )

    w2c = torch.tensor(np.linalg.inv(c2w), dtype=torch.float32)
    rects = [_screen_rect(bounds.cpu(), w2c, intrinsics, width, height) for _, _, bounds in _object_bounds(scene)]

    def cast_at(ox: float, oy: float) -> tuple[torch.Tensor, torch.Tensor]:
        cam = torch.stack([(u + ox - cx) / fx, (v + oy - cy) / fy, torch.ones_like(u)], dim=-1)
        return cast(scene, origin, cam @ rotation.T, rects)

    depth, color = cast_at(0.5, 0.5)
    if supersample > 1:
        offsets = [(k + 0.5) / supersample for k in range(supersample)]
        total = torch.zeros_like(color)
        for oy in offsets:
            for ox in offsets:
                total = total + cast_at(ox, oy)[1]
        color = total / supersample**2
    color = color.clamp(0, 1)
    return (color * 255 + 0.5).to(torch.uint8).cpu().numpy(), depth.cpu().numpy().astype(np.float32)


def sequence(
    config: SyntheticConfig, device: torch.device = CPU
) -> tuple[np.ndarray, Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """-> (intrinsics [3, 3], an iterator of (colour, depth, camera-to-world) per frame), ray cast
    on `device` (a GPU generates a 1200x680 frame in milliseconds, a CPU core in a tenth of a second)."""
    scene = make_scene(config.seed, symmetric=config.trap).to(device)
    poses = trajectory(config, config.frames)
    intrinsics = default_intrinsics(config.width, config.height)
    supersample = 2 if config.width * config.height <= 320 * 240 else 1

    def frames() -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        for c2w in poses:
            color, depth = render_view(scene, c2w, intrinsics, config.width, config.height, supersample)
            yield color, depth, c2w

    return intrinsics, frames()


def synthetic_for(config: SyntheticConfig, device: torch.device) -> SyntheticConfig:
    """Fill the sizes left at 0 for `device` (a closed path's frames: all of it, on any device)."""
    width, height, frames = SYNTHETIC_GPU if device.type == "cuda" else SYNTHETIC_CPU
    if path_turns(config):
        frames = closed_path_frames(config)
        if frames > MAX_SYNTHETIC_FRAMES:
            raise UserError(
                f"synthetic.loops={config.loops} at synthetic.speed={config.speed:g} and synthetic.fps={config.fps:g} "
                f"makes {frames:,} frames (at most {MAX_SYNTHETIC_FRAMES:,}): fewer loops, or a faster speed"
            )
    return replace(config, frames=config.frames or frames, width=config.width or width, height=config.height or height)
