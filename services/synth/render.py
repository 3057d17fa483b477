"""The synthetic world: a textured room with furniture and moving objects, rendered by ray casting.

``SynthWorld(cfg).render(i)`` returns a :class:`SynthFrame` with exact ground truth. Pure numpy, no I/O.

Dynamic mask choice: a pixel is *dynamic* when it shows an instance that moves at any time in the sequence
(the walking person, the chair that is moved), also in frames where that object happens to stand still —
this is what a map should leave out. With ``moved_chair=False`` that chair never moves and counts as static.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from services.common.errors import ConfigError
from services.synth.camera import intrinsics, trajectory
from services.synth.config import SynthConfig
from services.synth.layout import LABEL_NAMES, ROOM_FACE_LABELS, Instance, build_instances
from services.synth.raycast import cast_box, cast_room, safe_inverse, screen_region
from services.synth.textures import TextureAtlas, make_texture, surface_rng, texture_size

TANGENTS = np.array([[1, 2], [0, 2], [0, 1]])  # texture (u, v) axes of a face whose normal is along axis 0/1/2
AMBIENT = 0.45  # light reaching every surface
DIFFUSE = 0.9  # Lambertian gain of the ceiling point light
FALLOFF = 0.04  # 1 / (1 + FALLOFF · r²) attenuation of the light, r in metres
LIGHT_BELOW_CEILING = 0.2  # metres between the ceiling and the point light above the room centre


@dataclass(frozen=True)
class SynthFrame:
    """One rendered frame with its ground truth."""

    index: int  # frame index i (0-based)
    t_ns: int  # timestamp, int nanoseconds
    rgb: np.ndarray  # (H, W, 3) uint8 RGB
    depth: np.ndarray  # (H, W) float32 metres, z in the camera frame (> 0 everywhere: the room is closed)
    labels: np.ndarray  # (H, W) int32 index into world.label_names
    instance: np.ndarray  # (H, W) int32 index into world.instances, -1 on floor / walls / ceiling
    dynamic: np.ndarray  # (H, W) bool, pixel shows an instance that moves at some time in the sequence
    world_from_cam: np.ndarray  # (4, 4) float64, OpenCV camera (x right, y down, z forward)
    intrinsics: np.ndarray  # (4,) float64 (fx, fy, cx, cy), pixel centres at integer coordinates


@dataclass(frozen=True)
class InstanceBox:
    """World-space axis-aligned bounding box of one instance at one frame."""

    instance: int  # index into world.instances
    name: str  # instance name, e.g. "chair_moved"
    label: int  # index into world.label_names
    label_name: str
    lo: np.ndarray  # (3,) float64 metres, world
    hi: np.ndarray  # (3,) float64 metres, world
    dynamic: bool  # the instance moves at some time in the sequence


class SynthWorld:
    """Deterministic synthetic sequence defined by a :class:`SynthConfig` (textures built once here)."""

    def __init__(self, config: SynthConfig | None = None, poses: np.ndarray | None = None) -> None:
        """``poses``: an ``(n_frames, 4, 4)`` world_from_cam trajectory to render instead of the config's camera
        (motion profiles: bench/robustness.py)."""
        self.config = config or SynthConfig()
        cfg = self.config
        self.label_names: tuple[str, ...] = LABEL_NAMES
        self.instances: tuple[Instance, ...] = build_instances(cfg)
        self.intrinsics = intrinsics(cfg)
        self._poses = trajectory(cfg) if poses is None else np.asarray(poses, np.float64)
        if self._poses.shape != (cfg.n_frames, 4, 4):
            raise ConfigError(f"poses must be ({cfg.n_frames}, 4, 4) for n_frames={cfg.n_frames}, got {self._poses.shape}")
        self._room_hi = np.asarray(cfg.room_size, float)
        if not ((self._poses[:, :3, 3] > 0) & (self._poses[:, :3, 3] < self._room_hi)).all():
            raise ConfigError("camera trajectory leaves the room; reduce orbit_radius or enlarge room_size")
        parts = [(k, p) for k, inst in enumerate(self.instances) for p in inst.parts]
        self._part_instance = np.array([-1] + [k for k, _ in parts], np.int32)  # row 0: the room
        label_of = {n: j for j, n in enumerate(LABEL_NAMES)}
        surf_label = [label_of[n] for n in ROOM_FACE_LABELS]
        for k, _ in parts:
            surf_label += [label_of[self.instances[k].label]] * 6
        self._surface_label = np.array(surf_label, np.int32)
        self._dynamic_instance = np.array([inst.dynamic for inst in self.instances] + [False])  # [-1] → False
        self._atlas = self._build_atlas()
        fx, fy, cx, cy = self.intrinsics
        v, u = np.mgrid[0:cfg.height, 0:cfg.width].astype(np.float64)
        self._rays_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)]).reshape(3, -1)  # (3, HW) z = 1

    def _build_atlas(self) -> TextureAtlas:
        cfg, ppm = self.config, self.config.texels_per_metre
        textures = []
        for face in range(6):  # room faces
            tu, tv = TANGENTS[face // 2]
            h, w = texture_size(self._room_hi[tu], self._room_hi[tv], ppm)
            textures.append(make_texture(surface_rng(cfg.seed, "room", 0, face), h, w, ROOM_FACE_LABELS[face], ppm))
        for inst in self.instances:
            for j, part in enumerate(inst.parts):
                extent = np.asarray(part.hi) - np.asarray(part.lo)
                for face in range(6):
                    tu, tv = TANGENTS[face // 2]
                    h, w = texture_size(extent[tu], extent[tv], ppm)
                    textures.append(make_texture(surface_rng(cfg.seed, inst.name, j, face), h, w, inst.label, ppm))
        return TextureAtlas.pack(textures, ppm)

    # --- sequence-level ground truth -------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.config.n_frames

    def __iter__(self) -> Iterator[SynthFrame]:
        return (self.render(i) for i in range(len(self)))

    def sequence_time(self, i: int) -> float:
        """Sequence time s ∈ [0, 1] of frame i (drives all motion)."""
        return i / max(self.config.n_frames - 1, 1)

    def t_ns(self, i: int) -> int:
        """Timestamp of frame i in int nanoseconds."""
        return int(self.config.t0_ns + round(i * 1e9 / self.config.fps))

    def timestamps_ns(self) -> np.ndarray:
        """Timestamps (N,) int64 nanoseconds of all frames."""
        return np.array([self.t_ns(i) for i in range(len(self))], np.int64)

    @property
    def poses(self) -> np.ndarray:
        """world_from_cam (N, 4, 4) float64 of all frames (a copy)."""
        return self._poses.copy()

    def world_from_cam(self, i: int) -> np.ndarray:
        """world_from_cam (4, 4) float64 of frame i (a copy)."""
        return self._poses[self._check_index(i)].copy()

    def part_boxes(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World boxes of every part at frame i: lo (B, 3), hi (B, 3) float64 metres, instance (B,) int32."""
        s = self.sequence_time(self._check_index(i))
        los, his = zip(*(inst.boxes_at(s) for inst in self.instances))
        return np.concatenate(los), np.concatenate(his), self._part_instance[1:].copy()

    def instance_boxes(self, i: int) -> list[InstanceBox]:
        """World bounding box (union of parts) of every instance at frame i."""
        s = self.sequence_time(self._check_index(i))
        out = []
        for k, inst in enumerate(self.instances):
            lo, hi = inst.boxes_at(s)
            out.append(InstanceBox(k, inst.name, LABEL_NAMES.index(inst.label), inst.label,
                                   lo.min(axis=0), hi.max(axis=0), inst.dynamic))
        return out

    def _check_index(self, i: int) -> int:
        if not 0 <= i < len(self):
            raise IndexError(f"frame index {i} outside [0, {len(self)})")
        return i

    # --- rendering ----------------------------------------------------------------------------------------------
    def render(self, i: int) -> SynthFrame:
        """Render frame i (deterministic: same config and i → identical arrays)."""
        cfg = self.config
        pose = self._poses[self._check_index(i)]
        origin = pose[:3, 3]
        d = (pose[:3, :3] @ self._rays_cam).reshape(3, cfg.height, cfg.width).astype(np.float32)  # camera z = 1
        inv = safe_inverse(d)
        hits = cast_room(origin, d, inv, self._room_hi)
        cam_from_world = np.linalg.inv(pose)
        lo, hi, _ = self.part_boxes(i)
        for b in range(lo.shape[0]):
            region = screen_region(lo[b], hi[b], cam_from_world, self.intrinsics, hits.depth.shape, cfg.near)
            if region is not None:
                cast_box(hits, origin, d, inv, lo[b], hi[b], region, b + 1, cfg.near)
        rgb = self._shade(hits, origin, d, np.concatenate([np.zeros((1, 3)), lo]))
        if cfg.pixel_noise_std > 0:
            noise = np.random.default_rng([cfg.seed, 2, i]).normal(0.0, cfg.pixel_noise_std, rgb.shape)
            rgb = rgb + noise.astype(np.float32)
        instance = self._part_instance[hits.box]
        return SynthFrame(
            index=i, t_ns=self.t_ns(i), rgb=np.clip(rgb + 0.5, 0, 255).astype(np.uint8), depth=hits.depth,
            labels=self._surface_label[hits.box * 6 + hits.face], instance=instance,
            dynamic=self._dynamic_instance[instance], world_from_cam=pose.copy(), intrinsics=self.intrinsics.copy(),
        )

    def _shade(self, hits, origin: np.ndarray, d: np.ndarray, box_lo: np.ndarray) -> np.ndarray:
        """Texture colour × (ambient + point-light Lambertian) per pixel → (H, W, 3) float32 in 0..255."""
        box, face = hits.box, hits.face.astype(np.int32)
        lo = box_lo.astype(np.float32)[box]  # (H, W, 3): surface coordinates are relative to the box's min corner
        p = [np.float32(origin[k]) + hits.depth * d[k] for k in range(3)]  # world hit point planes
        local = [p[k] - lo[..., k] for k in range(3)]
        axis, side = face // 2, face % 2
        u = np.where(axis == 0, local[1], local[0])  # tangents: x-faces (y, z), y-faces (x, z), z-faces (x, y)
        v = np.where(axis == 2, local[1], local[2])
        colour = self._atlas.sample(box * 6 + face, u, v)
        outward = np.where(box == 0, 1 - 2 * side, 2 * side - 1).astype(np.float32)  # room normals point inward
        light = (self._room_hi[0] / 2, self._room_hi[1] / 2, self._room_hi[2] - LIGHT_BELOW_CEILING)
        to_light = [np.float32(light[k]) - p[k] for k in range(3)]
        dist2 = to_light[0] ** 2 + to_light[1] ** 2 + to_light[2] ** 2
        cos = outward * np.choose(axis, to_light) / np.sqrt(dist2)
        shade = AMBIENT + DIFFUSE * np.clip(cos, 0, None) / (1.0 + FALLOFF * dist2)
        return colour * shade[..., None].astype(np.float32)
