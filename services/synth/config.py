"""Configuration of the synthetic world: one frozen dataclass, validated on construction."""

from __future__ import annotations

from dataclasses import dataclass

from services.common.errors import ConfigError

CAMERA_MODES = ("orbit", "pan", "static")


@dataclass(frozen=True)
class SynthConfig:
    """Everything that defines a synthetic sequence. Same config → bit-identical frames.

    World frame: metres, z up, the room spans ``[0, room_size[0]] × [0, room_size[1]] × [0, room_size[2]]``.
    Sequence time ``s = i / (n_frames - 1)`` in [0, 1] drives every motion (camera and objects), so fewer
    frames means more motion per frame; for the default per-frame motion in a short test, keep n_frames and
    render only the frames needed (rendering is per frame, textures are built once).
    """

    width: int = 512  # image width in pixels
    height: int = 384  # image height in pixels
    n_frames: int = 200  # number of frames in the sequence
    fps: float = 10.0  # frame rate; frame i has t_ns = t0_ns + round(i * 1e9 / fps)
    t0_ns: int = 0  # timestamp of frame 0 in nanoseconds
    seed: int = 0  # seeds textures, camera shake phases and pixel noise
    hfov_deg: float = 60.0  # horizontal field of view in degrees (square pixels: fy = fx)

    camera: str = "orbit"  # "orbit": arc around the table; "pan": fixed position, yaw sweep; "static": fixed pose
    orbit_radius: float = 2.4  # metres from the room centre to the camera path ("orbit" mode)
    orbit_span_deg: float = 100.0  # arc swept over the whole sequence ("orbit" mode), degrees
    pan_span_deg: float = 50.0  # peak-to-peak yaw sweep ("pan" mode), degrees
    camera_height: float = 1.5  # camera height above the floor, metres
    static_at: float = 0.5  # sequence time s whose orbit pose the "static" camera keeps
    shake_translation: float = 0.015  # hand-held shake amplitude, metres (0 disables; ignored when static)
    shake_rotation_deg: float = 0.4  # hand-held shake amplitude, degrees (0 disables; ignored when static)

    person: bool = True  # a person walks across the room (dynamic)
    moved_chair: bool = True  # one chair slides to a new place; if False it stays put and counts as static
    person_walk: tuple[float, float] = (0.15, 0.55)  # sequence-time interval during which the person walks
    chair_move: tuple[float, float] = (0.6, 0.75)  # sequence-time interval during which the chair slides

    room_size: tuple[float, float, float] = (7.0, 6.0, 2.8)  # room extent along x, y, z in metres
    texels_per_metre: float = 128.0  # texture resolution on every surface
    near: float = 0.05  # rays ignore hits closer than this, metres
    pixel_noise_std: float = 0.0  # std of Gaussian noise added to rgb (0..255 scale); 0 keeps rgb exact

    def __post_init__(self) -> None:
        if self.camera not in CAMERA_MODES:
            raise ConfigError(f"camera must be one of {CAMERA_MODES}, got {self.camera!r}")
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"image must be at least 8x8, got {self.width}x{self.height}")
        if self.n_frames < 1:
            raise ConfigError(f"n_frames must be >= 1, got {self.n_frames}")
        if self.fps <= 0:
            raise ConfigError(f"fps must be > 0, got {self.fps}")
        if not 1.0 <= self.hfov_deg <= 170.0:
            raise ConfigError(f"hfov_deg must be in [1, 170], got {self.hfov_deg}")
        for name in ("person_walk", "chair_move"):
            a, b = getattr(self, name)
            if not 0.0 <= a < b <= 1.0:
                raise ConfigError(f"{name} must satisfy 0 <= start < end <= 1, got {(a, b)}")
        if min(self.room_size) <= 0:
            raise ConfigError(f"room_size must be positive, got {self.room_size}")
        if self.texels_per_metre <= 0 or self.near <= 0 or self.pixel_noise_std < 0:
            raise ConfigError("texels_per_metre and near must be > 0, pixel_noise_std >= 0")
