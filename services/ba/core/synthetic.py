"""Synthetic static BA windows with exact poses, depth and flow targets (for tests and benchmarks).

Depth is a smooth random field (sum of low-frequency sinusoids); flow targets are exact reprojections.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

from services.ba.core import projective, se3
from services.ba.core.ba import BAProblem, BAState


class SyntheticWindow(NamedTuple):
    """Ground truth and observations of one window."""

    truth: BAState  # exact poses (world_from_cam), disparities (N, h, w) and grid intrinsics
    problem: BAProblem  # exact targets, confidence 1 inside the image (0 outside / behind)


def smooth_depth(n: int, h: int, w: int, gen: torch.Generator, near: float = 2.0, far: float = 5.0) -> torch.Tensor:
    """``(n, h, w)`` float64 depths in ``[near, far]`` from random low-frequency sinusoids."""
    ys = torch.linspace(0, 1, h, dtype=torch.float64)[:, None]
    xs = torch.linspace(0, 1, w, dtype=torch.float64)[None, :]
    field = torch.zeros(n, h, w, dtype=torch.float64)
    for _ in range(4):  # a few octaves; not an inner-loop of the solver
        fx, fy, ph = (torch.rand(3, n, 1, 1, generator=gen, dtype=torch.float64) * torch.tensor(
            [3.0, 3.0, 2 * math.pi], dtype=torch.float64)[:, None, None, None])
        field = field + torch.sin(2 * math.pi * (fx * xs + fy * ys) + ph)
    field = (field - field.amin((1, 2), keepdim=True)) / (field.amax((1, 2), keepdim=True)
                                                         - field.amin((1, 2), keepdim=True))
    return near + (far - near) * field


def room_depth(poses: torch.Tensor, intrinsics: torch.Tensor, h: int, w: int,
               room_lo=(-1.5, -1.2, -2.0), room_hi=(2.5, 1.0, 3.0)) -> torch.Tensor:
    """``(N, h, w)`` depth of the inside of an axis-aligned box room seen from ``poses`` (consistent geometry)."""
    n = poses.shape[0]
    q = projective.unproject(projective.pixel_grid(h, w, poses.dtype), torch.zeros(()), intrinsics)[..., :3]
    rays = (poses[:, None, :3, :3] @ q[None, :, :, None])[..., 0]  # (N, P, 3) world directions, z_cam = 1
    origin = poses[:, None, :3, 3]
    lo = torch.tensor(room_lo, dtype=poses.dtype)
    hi = torch.tensor(room_hi, dtype=poses.dtype)
    safe = torch.where(rays.abs() < 1e-12, torch.full_like(rays, 1e-12), rays)
    # from inside the box the ray leaves through the nearest wall on the side it points to
    exit_t = torch.where(rays > 0, (hi - origin) / safe, (lo - origin) / safe)
    return exit_t.amin(-1).reshape(n, h, w)


def world_codes(truth: BAState, k: int, freq: float, seed: int) -> torch.Tensor:
    """``(N, h, w, k)`` codes that are a smooth function (random Fourier features) of each pixel's world point."""
    n, h, w = truth.disparity.shape
    pts = projective.unproject(projective.pixel_grid(h, w, truth.poses.dtype), truth.disparity.reshape(n, -1),
                               truth.intrinsics)
    world = (truth.poses[:, None] @ (pts / pts[..., 3:])[..., None])[..., :3, 0]
    gen = torch.Generator().manual_seed(seed)
    proj = torch.randn(3, k, generator=gen, dtype=truth.poses.dtype) * freq
    phase = torch.rand(k, generator=gen, dtype=truth.poses.dtype) * 2 * math.pi
    return torch.sin(world @ proj + phase).reshape(n, h, w, k)


def trajectory(n: int, gen: torch.Generator, step: float = 0.12, turn_deg: float = 1.5) -> torch.Tensor:
    """``(n, 4, 4)`` world_from_cam poses: sideways/forward motion with small rotations; pose 0 = identity."""
    xi = torch.zeros(n, 6, dtype=torch.float64)
    k = torch.arange(n, dtype=torch.float64)
    xi[:, 0], xi[:, 1], xi[:, 2] = step * k, 0.02 * torch.sin(k), 0.3 * step * k
    xi[:, 3:] = math.radians(turn_deg) * k[:, None] * torch.randn(1, 3, generator=gen, dtype=torch.float64)
    poses = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    poses[:, :3, :3] = se3.so3_exp(xi[:, 3:])
    poses[:, :3, 3] = xi[:, :3]
    return poses


def temporal_edges(n: int, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All directed pairs ``(i, j)`` with ``0 < |i - j| <= radius``."""
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    keep = ((i - j).abs() <= radius) & (i != j)
    return i[keep], j[keep]


def make_window(n: int = 6, h: int = 24, w: int = 32, focal: float = 28.0, radius: int = 2,
                seed: int = 0, surface: str = "random", step: float = 0.12,
                principal_offset: tuple[float, float] = (0.0, 0.0)) -> SyntheticWindow:
    """Exact static window: ``n`` keyframes on an ``h x w`` grid with grid focal ``focal``, the principal point
    ``principal_offset`` grid px from the grid's centre.

    ``surface="random"``: an independent smooth depth map per keyframe (flow targets are still exact, but the
    keyframes do not see one common surface); ``surface="room"``: the inside of a box room (one consistent
    world, so world-anchored codes agree across views). ``step``: camera motion per keyframe (m).
    """
    gen = torch.Generator().manual_seed(seed)
    poses = trajectory(n, gen, step=step)
    intr = torch.tensor([focal, focal, (w - 1) / 2 + principal_offset[0], (h - 1) / 2 + principal_offset[1]],
                        dtype=torch.float64)
    if surface == "random":
        disp = 1 / smooth_depth(n, h, w, gen)
    elif surface == "room":
        disp = 1 / room_depth(poses, intr, h, w)
    else:
        raise ValueError(f"surface must be 'random' or 'room', got {surface!r}")
    ii, jj = temporal_edges(n, radius)
    rp = projective.reproject(poses[ii], poses[jj], disp.reshape(n, -1)[ii],
                              projective.pixel_grid(h, w), intr, with_jacobians=False)
    x, y = rp.coords[..., 0], rp.coords[..., 1]
    inside = rp.valid & (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    problem = BAProblem(ii, jj, rp.coords.view(-1, h, w, 2), inside.to(torch.float64).view(-1, h, w))
    return SyntheticWindow(BAState(poses, disp, intr), problem)


def perturb_poses(poses: torch.Tensor, trans_m: float, rot_deg: float, gen: torch.Generator,
                  keep_first: int = 1) -> torch.Tensor:
    """Move every pose but the first ``keep_first`` by exactly ``trans_m`` and ``rot_deg`` in random directions."""
    n = poses.shape[0]
    t_dir = torch.randn(n, 3, generator=gen, dtype=poses.dtype)
    r_dir = torch.randn(n, 3, generator=gen, dtype=poses.dtype)
    delta = torch.eye(4, dtype=poses.dtype).repeat(n, 1, 1)
    delta[:, :3, :3] = se3.so3_exp(math.radians(rot_deg) * r_dir / r_dir.norm(dim=-1, keepdim=True))
    delta[:, :3, 3] = trans_m * t_dir / t_dir.norm(dim=-1, keepdim=True)
    out = poses @ delta  # perturbation in the camera frame
    out[:keep_first] = poses[:keep_first]
    return out
