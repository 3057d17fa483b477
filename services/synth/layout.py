"""Scene layout: the room, its furniture and the objects that move, as axis-aligned boxes.

World frame: metres, z up, floor at z = 0, the room spans [0, X] × [0, Y] × [0, Z] (``SynthConfig.room_size``).
Every object instance is a rigid set of boxes ("parts") given in instance-local coordinates (origin on the
floor below the object's centre); its origin moves along a :class:`Motion` over sequence time s ∈ [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.synth.config import SynthConfig

# Stable label order: indices never depend on which objects a config enables.
LABEL_NAMES: tuple[str, ...] = (
    "floor", "wall", "ceiling", "door", "table", "chair", "shelf", "cabinet",
    "sofa", "monitor", "fire extinguisher", "plant", "person",
)
ROOM_FACE_LABELS: tuple[str, ...] = ("wall", "wall", "wall", "wall", "floor", "ceiling")  # faces -x,+x,-y,+y,-z,+z


@dataclass(frozen=True)
class Box:
    """Axis-aligned box in instance-local coordinates, metres: ``lo`` (3,) < ``hi`` (3,)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


@dataclass(frozen=True)
class Motion:
    """Origin of an instance over sequence time: at ``start`` until ``t_begin``, eased to ``end`` by ``t_end``."""

    start: tuple[float, float, float]  # world position (metres) before the move
    end: tuple[float, float, float]  # world position (metres) after the move
    t_begin: float = 0.0  # sequence time at which the move starts
    t_end: float = 1.0  # sequence time at which the move ends

    @property
    def moves(self) -> bool:
        return self.start != self.end

    def position(self, s: float) -> np.ndarray:
        """World position (3,) float64 of the instance origin at sequence time ``s`` ∈ [0, 1]."""
        a = np.clip((s - self.t_begin) / (self.t_end - self.t_begin), 0.0, 1.0)
        ease = a * a * (3.0 - 2.0 * a)  # smoothstep: zero velocity at both ends of the move
        return np.asarray(self.start, float) + ease * (np.asarray(self.end, float) - np.asarray(self.start, float))


@dataclass(frozen=True)
class Instance:
    """One object: its semantic label, its parts and its motion. ``dynamic`` iff it moves at any time."""

    name: str  # unique instance name, e.g. "chair_moved"
    label: str  # one of LABEL_NAMES
    parts: tuple[Box, ...]
    motion: Motion

    @property
    def dynamic(self) -> bool:
        return self.motion.moves

    def boxes_at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """World boxes of all parts at sequence time ``s``: ``(lo, hi)``, each (P, 3) float64 metres."""
        origin = self.motion.position(s)
        lo = np.array([p.lo for p in self.parts], float) + origin
        hi = np.array([p.hi for p in self.parts], float) + origin
        return lo, hi


def _legs(half_x: float, half_y: float, height: float, size: float) -> list[Box]:
    """Four square legs of side ``size`` under a rectangle of half extents (half_x, half_y)."""
    legs = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (half_x - size / 2), sy * (half_y - size / 2)
            legs.append(Box((cx - size / 2, cy - size / 2, 0.0), (cx + size / 2, cy + size / 2, height)))
    return legs


def _chair(back_side: str) -> tuple[Box, ...]:
    """A chair: seat, backrest on ``back_side`` ("+y" or "-x"), four legs."""
    seat = Box((-0.22, -0.22, 0.42), (0.22, 0.22, 0.46))
    back = Box((-0.22, 0.18, 0.46), (0.22, 0.22, 0.92)) if back_side == "+y" else \
        Box((-0.22, -0.22, 0.46), (-0.18, 0.22, 0.92))
    return (seat, back, *_legs(0.22, 0.22, 0.42, 0.04))


def _person() -> tuple[Box, ...]:
    """A 1.75 m person facing +x: legs, torso, arms, neck, head."""
    return (
        Box((-0.07, -0.13, 0.0), (0.07, -0.01, 0.85)), Box((-0.07, 0.01, 0.0), (0.07, 0.13, 0.85)),
        Box((-0.10, -0.20, 0.85), (0.10, 0.20, 1.45)),
        Box((-0.06, -0.28, 0.80), (0.06, -0.20, 1.42)), Box((-0.06, 0.20, 0.80), (0.06, 0.28, 1.42)),
        Box((-0.04, -0.04, 1.45), (0.04, 0.04, 1.50)), Box((-0.10, -0.09, 1.50), (0.10, 0.09, 1.75)),
    )


def _still(x: float, y: float) -> Motion:
    return Motion((x, y, 0.0), (x, y, 0.0))


def table_centre(cfg: SynthConfig) -> np.ndarray:
    """World point (3,) the orbiting camera looks at: the middle of the table top."""
    sx, sy, _ = cfg.room_size
    return np.array([sx / 2, sy / 2 + 0.2, 0.8])


def build_instances(cfg: SynthConfig) -> tuple[Instance, ...]:
    """The furniture and moving objects of the room, in a fixed order (person omitted when disabled)."""
    sx, sy, _ = cfg.room_size
    cx, cy = sx / 2, sy / 2
    insts = [
        Instance("table", "table", (Box((-0.7, -0.4, 0.72), (0.7, 0.4, 0.76)), *_legs(0.7, 0.4, 0.72, 0.05)),
                 _still(cx, cy + 0.2)),
        Instance("monitor", "monitor", (Box((-0.25, -0.03, 0.80), (0.25, 0.03, 1.10)),
                                        Box((-0.04, -0.04, 0.76), (0.04, 0.04, 0.80))), _still(cx, cy + 0.35)),
        Instance("chair_static", "chair", _chair("+y"), _still(cx + 0.3, cy + 1.0)),
        Instance("shelf", "shelf", (Box((-0.8, -0.2, 0.0), (0.8, 0.2, 1.9)),), _still(1.4, sy - 0.2)),
        Instance("cabinet", "cabinet", (Box((-0.5, -0.25, 0.0), (0.5, 0.25, 1.1)),), _still(sx - 1.9, sy - 0.25)),
        Instance("sofa", "sofa", (
            Box((-0.45, -1.0, 0.0), (0.45, 1.0, 0.45)), Box((-0.45, -1.0, 0.45), (-0.25, 1.0, 0.90)),
            Box((-0.25, -1.0, 0.45), (0.45, -0.85, 0.65)), Box((-0.25, 0.85, 0.45), (0.45, 1.0, 0.65)),
        ), _still(0.45, cy)),
        Instance("fire_extinguisher", "fire extinguisher", (
            Box((-0.09, -0.09, 0.0), (0.09, 0.09, 0.55)), Box((-0.04, -0.04, 0.55), (0.04, 0.04, 0.62)),
        ), _still(sx - 0.15, sy - 1.0)),
        Instance("plant", "plant", (Box((-0.2, -0.2, 0.0), (0.2, 0.2, 0.35)), Box((-0.3, -0.3, 0.35), (0.3, 0.3, 1.1))),
                 _still(sx - 0.45, sy - 0.45)),
        Instance("door", "door", (Box((-0.03, -0.45, 0.0), (0.0, 0.45, 2.05)),), _still(sx, 2.0)),
    ]
    chair_start = (cx - 1.05, cy + 0.2, 0.0)
    chair_end = (cx - 2.0, cy - 0.9, 0.0) if cfg.moved_chair else chair_start
    insts.append(Instance("chair_moved", "chair", _chair("-x"), Motion(chair_start, chair_end, *cfg.chair_move)))
    if cfg.person:
        insts.append(Instance("person", "person", _person(),
                              Motion((1.2, sy - 1.3, 0.0), (sx - 1.3, sy - 1.3, 0.0), *cfg.person_walk)))
    return tuple(insts)
