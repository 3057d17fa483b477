"""Procedural colour textures, one image per surface, packed into one atlas image for vectorised sampling.

Textures live in surface coordinates (metres along the face's two tangent axes), so they stick to the
surface in 3D. Every texture mixes multi-scale colour value noise (down to 2-texel cells, so dense optical
flow has texture to lock onto) with a per-label pattern (planks, posters, books, grain, stripes, leaves).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import cv2
import numpy as np

# label -> (base RGB, pattern name)
APPEARANCE: dict[str, tuple[tuple[int, int, int], str]] = {
    "floor": ((150, 110, 75), "planks"),
    "wall": ((200, 195, 180), "posters"),
    "ceiling": ((225, 225, 220), "plain"),
    "door": ((120, 80, 50), "grain"),
    "table": ((170, 120, 70), "grain"),
    "chair": ((60, 90, 150), "stripes"),
    "shelf": ((110, 75, 45), "books"),
    "cabinet": ((180, 180, 170), "grain"),
    "sofa": ((140, 40, 45), "stripes"),
    "monitor": ((35, 35, 40), "plain"),
    "fire extinguisher": ((200, 25, 20), "plain"),
    "plant": ((50, 120, 45), "leaves"),
    "person": ((70, 60, 110), "stripes"),
}
MAX_TEXTURE_SIDE = 2048  # texels; caps memory for very large rooms
ATLAS_WIDTH = 4096  # texels
CV_MAX_SIDE = 32767  # cv2.remap needs image sides below this


def surface_rng(seed: int, name: str, part: int, face: int) -> np.random.Generator:
    """Generator for one surface, stable under adding/removing other objects (keyed by instance name)."""
    return np.random.default_rng([seed, zlib.crc32(name.encode()), part, face])


def value_noise(rng: np.random.Generator, h: int, w: int, cell: int, channels: int) -> np.ndarray:
    """Smooth noise (h, w, channels) float32 in about [-1, 1] with feature size ``cell`` texels."""
    gh, gw = h // cell + 3, w // cell + 3
    grid = rng.uniform(-1.0, 1.0, (gh, gw, channels)).astype(np.float32)
    big = cv2.resize(grid, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)
    big = big.reshape(gh * cell, gw * cell, channels)
    oy, ox = rng.integers(0, cell, 2)
    return big[oy:oy + h, ox:ox + w]


def _planks(rng, tex, ppm):
    plank = max(2, int(0.18 * ppm))
    rows = np.arange(tex.shape[0]) // plank
    tint = rng.uniform(0.75, 1.2, (rows.max() + 1, 3)).astype(np.float32)
    tex *= tint[rows][:, None, :]
    tex[np.arange(tex.shape[0]) % plank == 0] *= 0.5  # dark seams between planks


def _posters(rng, tex, ppm):
    h, w = tex.shape[:2]
    for _ in range(int(h * w / ppm ** 2 * 1.5) + 2):  # about 1.5 posters / blobs per square metre
        colour = rng.uniform(20, 255, 3).tolist()
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            dx, dy = rng.integers(int(0.1 * ppm) + 1, int(0.5 * ppm) + 2, 2)
            cv2.rectangle(tex, (x, y), (x + int(dx), y + int(dy)), colour, -1)
        else:
            cv2.circle(tex, (x, y), int(rng.integers(2, int(0.25 * ppm) + 3)), colour, -1)


def _books(rng, tex, ppm):
    h, w = tex.shape[:2]
    board = max(2, int(0.38 * ppm))
    x = 0
    while x < w:  # vertical book spines of random width and colour
        bw = int(rng.integers(max(1, int(0.02 * ppm)), int(0.07 * ppm) + 2))
        tex[:, x:x + bw] = rng.uniform(30, 240, 3)
        x += bw
    tex[np.arange(h) % board < max(1, int(0.03 * ppm))] = (90, 60, 35)  # shelf boards


def _grain(rng, tex, ppm):
    h, w = tex.shape[:2]
    warp = value_noise(rng, h, w, max(2, int(0.3 * ppm)), 1)[..., 0]
    v = np.arange(h, dtype=np.float32)[:, None] / ppm
    tex *= (1.0 + 0.18 * np.sin(2 * np.pi * (v * 25.0 + 2.0 * warp)))[..., None]


def _stripes(rng, tex, ppm):
    h, w = tex.shape[:2]
    ang = rng.uniform(0, np.pi)
    period = rng.uniform(0.04, 0.12) * ppm
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    phase = (np.cos(ang) * xx + np.sin(ang) * yy) / period
    tex *= (1.0 + 0.3 * np.sign(np.sin(2 * np.pi * phase)))[..., None]


def _leaves(rng, tex, ppm):
    h, w = tex.shape[:2]
    for _ in range(int(h * w / ppm ** 2 * 400) + 4):
        colour = (rng.uniform(10, 90), rng.uniform(70, 200), rng.uniform(10, 70))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        cv2.circle(tex, (x, y), int(rng.integers(1, max(2, int(0.03 * ppm)))), colour, -1)


PATTERNS = {"planks": _planks, "posters": _posters, "books": _books, "grain": _grain,
            "stripes": _stripes, "leaves": _leaves, "plain": lambda rng, tex, ppm: None}


def make_texture(rng: np.random.Generator, h: int, w: int, label: str, ppm: float) -> np.ndarray:
    """Texture image (h, w, 3) uint8 RGB for a surface of ``label`` at ``ppm`` texels per metre."""
    base, pattern = APPEARANCE[label]
    tex = np.empty((h, w, 3), np.float32)
    tex[:] = np.clip(np.asarray(base, np.float32) * rng.uniform(0.85, 1.15, 3), 0, 255)
    tex *= 1.0 + 0.25 * value_noise(rng, h, w, max(2, int(0.5 * ppm)), 1)
    PATTERNS[pattern](rng, tex, ppm)
    for cell, amp in ((16, 26.0), (4, 22.0), (2, 12.0)):  # detail at several scales for optical flow,
        tex += amp * (0.7 * value_noise(rng, h, w, cell, 1) + 0.3 * value_noise(rng, h, w, cell, 3))  # mostly grey
    return np.clip(tex, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class TextureAtlas:
    """All surface textures shelf-packed into one image, so one ``cv2.remap`` samples every pixel.

    Surface k's texel (row y, column x) is ``image[row0[k] + y, col0[k] + x]``.
    """

    image: np.ndarray  # (AH, AW, 3) uint8 RGB
    col0: np.ndarray  # (S,) float32 atlas column of each texture's first texel
    row0: np.ndarray  # (S,) float32 atlas row of each texture's first texel
    width: np.ndarray  # (S,) float32 texture width in texels (along the first tangent)
    height: np.ndarray  # (S,) float32 texture height in texels (along the second tangent)
    ppm: float  # texels per metre

    @staticmethod
    def pack(textures: list[np.ndarray], ppm: float) -> "TextureAtlas":
        """Shelf packing: tallest first, left to right in rows of at most ATLAS_WIDTH texels."""
        order = sorted(range(len(textures)), key=lambda k: -textures[k].shape[0])
        col0, row0 = np.zeros(len(textures), np.float32), np.zeros(len(textures), np.float32)
        x = y = shelf = 0
        for k in order:
            h, w = textures[k].shape[:2]
            if x + w > ATLAS_WIDTH:
                x, y, shelf = 0, y + shelf, 0
            col0[k], row0[k] = x, y
            x, shelf = x + w, max(shelf, h)
        if y + shelf >= CV_MAX_SIDE:
            raise ValueError(f"textures need an atlas {y + shelf} texels tall (max {CV_MAX_SIDE - 1}); "
                             "lower texels_per_metre or room_size")
        image = np.zeros((y + shelf, ATLAS_WIDTH, 3), np.uint8)
        for k, tex in enumerate(textures):
            image[int(row0[k]):int(row0[k]) + tex.shape[0], int(col0[k]):int(col0[k]) + tex.shape[1]] = tex
        width = np.array([t.shape[1] for t in textures], np.float32)
        height = np.array([t.shape[0] for t in textures], np.float32)
        return TextureAtlas(image, col0, row0, width, height, ppm)

    def sample(self, surface: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Bilinear colours (H, W, 3) uint8 at surface coordinates ``u, v`` (H, W) metres of surfaces (H, W) int.

        Coordinates are clamped to the texel centres of their own texture, so neighbours never bleed in.
        """
        tx = np.clip(u * np.float32(self.ppm) - 0.5, 0, self.width[surface] - 1) + self.col0[surface]
        ty = np.clip(v * np.float32(self.ppm) - 0.5, 0, self.height[surface] - 1) + self.row0[surface]
        return cv2.remap(self.image, tx.astype(np.float32), ty.astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)


def texture_size(extent_u: float, extent_v: float, ppm: float) -> tuple[int, int]:
    """Texture (height, width) in texels covering a face of ``extent_u × extent_v`` metres."""
    w = int(np.clip(np.ceil(extent_u * ppm) + 1, 2, MAX_TEXTURE_SIDE))
    h = int(np.clip(np.ceil(extent_v * ppm) + 1, 2, MAX_TEXTURE_SIDE))
    return h, w
