"""The numpy geometry the tracking process runs without torch (services/ba/core/se3_numpy.py, projective_numpy.py):
the same numbers as the torch core, which tests/test_ba_geometry.py checks against autograd, and its Jacobian by
central differences of its own reprojection."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from services.ba.core import projective, se3, se3_numpy
from services.ba.core.projective_numpy import induced_flow_field, pixel_grid, reproject_into, translational_parallax


def _tangents(n: int, rot_scale: float, seed: int = 0) -> np.ndarray:
    xi = np.random.default_rng(seed).normal(size=(n, 6))
    xi[:, 3:] *= rot_scale / np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    return xi


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 1e-3, 0.3, 2.0, np.pi - 1e-6])
def test_se3_matches_the_torch_core(angle):
    for xi in _tangents(8, angle):
        pose = se3_numpy.exp(xi)
        np.testing.assert_allclose(pose, se3.exp(torch.from_numpy(xi)).numpy(), rtol=0, atol=1e-14)
        np.testing.assert_allclose(se3_numpy.log(pose), se3.log(torch.from_numpy(pose)).numpy(), rtol=0, atol=1e-9)
        np.testing.assert_allclose(se3_numpy.inverse(pose) @ pose, np.eye(4), rtol=0, atol=1e-14)
        if angle < 3.0:  # log is exp's inverse inside the ball |phi| < pi
            np.testing.assert_allclose(se3_numpy.log(pose), xi, rtol=0, atol=1e-9)


def test_orthonormalize_matches_the_torch_core():
    pose = se3_numpy.exp(_tangents(1, 0.7)[0])
    pose[:3, :3] *= 1 + 1e-4  # off SO(3), as rounding leaves a product of poses
    ours = se3_numpy.orthonormalize(pose)
    np.testing.assert_allclose(ours, se3.orthonormalize(torch.from_numpy(pose)).numpy(), rtol=0, atol=1e-15)
    assert np.abs(ours[:3, :3].T @ ours[:3, :3] - np.eye(3)).max() < 1e-12
    np.testing.assert_allclose(se3_numpy.retract(pose, np.zeros(6)), ours, rtol=0, atol=1e-15)


def _scene(m: int = 3, h: int = 6, w: int = 8, seed: int = 1):
    rng = np.random.default_rng(seed)
    sources = np.stack([se3_numpy.exp(xi) for xi in _tangents(m, 0.2, seed) * 0.3])
    camera = se3_numpy.exp(_tangents(1, 0.25, seed + 1)[0] * 0.3)
    disparity = rng.uniform(0.1, 1.0, size=(m, h * w))
    return sources, camera, disparity, pixel_grid(h, w), np.array([5.0, 5.2, 3.5, 2.5])


def test_reprojection_into_a_camera_matches_the_torch_core():
    sources, camera, disparity, pixels, k = _scene()
    ours = reproject_into(sources, camera, disparity, pixels, k)
    theirs = projective.reproject(torch.from_numpy(sources), torch.from_numpy(camera).expand(len(sources), 4, 4),
                                  torch.from_numpy(disparity), torch.from_numpy(pixels), torch.from_numpy(k))
    np.testing.assert_allclose(ours.coords, theirs.coords.numpy(), rtol=0, atol=1e-12)
    assert np.array_equal(ours.valid, theirs.valid.numpy())
    np.testing.assert_allclose(ours.j_pose, theirs.j_pose_j.numpy(), rtol=0, atol=1e-10)


def test_the_camera_pose_jacobian_matches_central_differences():
    sources, camera, disparity, pixels, k = _scene(seed=3)
    jac = reproject_into(sources, camera, disparity, pixels, k).j_pose
    eps = 1e-6
    for axis in range(6):
        step = np.zeros(6)
        step[axis] = eps
        plus = reproject_into(sources, se3_numpy.exp(step) @ camera, disparity, pixels, k, False).coords
        minus = reproject_into(sources, se3_numpy.exp(-step) @ camera, disparity, pixels, k, False).coords
        np.testing.assert_allclose(jac[..., axis], (plus - minus) / (2 * eps), rtol=1e-6, atol=1e-6)


def test_points_behind_the_camera_are_invalid():
    source = np.eye(4)[None]
    behind = np.eye(4)
    behind[2, 3] = 5.0  # the camera 5 m ahead, looking the same way: points at 1 m are behind it
    rp = reproject_into(source, behind, np.full((1, 4), 1.0), pixel_grid(2, 2), np.array([2.0, 2.0, 0.5, 0.5]))
    assert not rp.valid.any()


def test_the_induced_flow_is_the_translation_parallax_at_every_working_pixel():
    h, w, grid = 6, 8, 8
    disparity = np.full((h, w), 0.5)  # a wall 2 m away
    k = np.array([50.0, 50.0, 3.5, 2.5])
    moved = np.eye(4)
    moved[0, 3] = 0.1  # 10 cm to the right: the wall moves left by f * t * d grid pixels
    flow = induced_flow_field(np.eye(4), moved, disparity, k, grid)
    assert flow.shape == (h * grid, w * grid, 2) and flow.dtype == np.float32
    np.testing.assert_allclose(flow[..., 0], -50.0 * 0.1 * 0.5 * grid, rtol=1e-5)
    np.testing.assert_allclose(flow[..., 1], 0.0, atol=1e-5)
    torch_args = [torch.from_numpy(a) for a in (np.eye(4), moved, disparity, k)]
    np.testing.assert_array_equal(induced_flow_field(*torch_args, grid), flow)  # mapping passes its tensors


def _project(pose: np.ndarray, points: np.ndarray, k: np.ndarray) -> np.ndarray:
    """World ``points`` (P, 3) into the camera ``pose`` (world_from_cam), by hand."""
    cam = (points - pose[:3, 3]) @ pose[:3, :3]
    return cam[:, :2] / cam[:, 2:] * k[:2] + k[2:]


def test_translational_parallax_is_what_the_translation_alone_moves():
    """A wall 2 m away seen from a camera 10 cm to the side moves f t d = 2.5 grid px; a camera that only turned
    makes none; a camera that turned and moved makes the median distance between where the wall's points land
    from its centre and from the first camera's (projected by hand here)."""
    h, w = 6, 8
    disparity = np.full((h, w), 0.5)
    k = np.array([50.0, 50.0, 3.5, 2.5])
    pixels = pixel_grid(h, w)
    wall = np.concatenate([(pixels - k[2:]) / k[:2], np.ones((len(pixels), 1))], axis=1) * 2.0
    side = np.eye(4)
    side[0, 3] = 0.1
    assert translational_parallax(np.eye(4), side, disparity, k) == pytest.approx(50.0 * 0.1 * 0.5, rel=1e-9)
    turned = np.eye(4)
    turned[:3, :3] = se3_numpy.exp(np.array([0.0, 0.0, 0.0, 0.02, -0.05, 0.01]))[:3, :3]
    assert translational_parallax(np.eye(4), turned, disparity, k) == pytest.approx(0.0, abs=1e-9)
    for moved_by in ([0.1, 0.0, 0.0], [0.03, -0.02, 0.5]):
        moved = turned.copy()
        moved[:3, 3] = moved_by
        want = np.median(np.linalg.norm(_project(moved, wall, k) - _project(turned, wall, k), axis=1))
        assert want > 1.0
        assert translational_parallax(np.eye(4), moved, disparity, k) == pytest.approx(want, rel=1e-9)
    torch_args = [torch.from_numpy(a) for a in (np.eye(4), moved, disparity, k)]
    assert translational_parallax(*torch_args) == translational_parallax(np.eye(4), moved, disparity, k)
