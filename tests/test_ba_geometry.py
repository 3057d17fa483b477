"""SE(3) and reprojection: round trips, known answers, analytic Jacobians vs torch.func.jacfwd (float64)."""
from __future__ import annotations

import math

import pytest
import torch

from services.ba.core import projective, se3, synthetic
from services.ba.frontend import edges

torch_dtype = torch.float64


def _random_tangent(n: int, gen: torch.Generator, rot_scale: float = 1.0) -> torch.Tensor:
    xi = torch.randn(n, 6, generator=gen, dtype=torch_dtype)
    xi[:, 3:] *= rot_scale
    return xi


def _assert_rel_close(a: torch.Tensor, b: torch.Tensor, rel: float = 1e-6) -> None:
    err = (a - b).abs().max().item()
    ref = max(b.abs().max().item(), 1e-12)
    assert err <= rel * ref, f"max abs err {err:.3e} vs scale {ref:.3e}"


@pytest.mark.parametrize("rot_scale", [1e-9, 1e-5, 0.3, 1.0, 2.5])
def test_exp_log_round_trip(rot_scale):
    gen = torch.Generator().manual_seed(0)
    xi = _random_tangent(64, gen, rot_scale)
    xi[:, 3:] = xi[:, 3:].clamp(-1.7, 1.7)  # keep |phi| < pi so log is the inverse
    pose = se3.exp(xi)
    torch.testing.assert_close(se3.log(pose), xi, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(se3.exp(se3.log(pose)), pose, rtol=1e-10, atol=1e-12)


def test_exp_matches_matrix_exponential():
    gen = torch.Generator().manual_seed(1)
    xi = _random_tangent(16, gen)
    alg = torch.zeros(16, 4, 4, dtype=torch_dtype)
    alg[:, :3, :3] = se3.hat(xi[:, 3:])
    alg[:, :3, 3] = xi[:, :3]
    torch.testing.assert_close(se3.exp(xi), torch.linalg.matrix_exp(alg), rtol=1e-10, atol=1e-12)


def test_rotation_is_orthonormal_and_quaternion_round_trip():
    gen = torch.Generator().manual_seed(2)
    rot = se3.so3_exp(torch.randn(32, 3, generator=gen, dtype=torch_dtype) * 2)
    eye = torch.eye(3, dtype=torch_dtype).expand(32, 3, 3)
    torch.testing.assert_close(rot @ rot.transpose(-1, -2), eye, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(32, dtype=torch_dtype))
    q = se3.rotation_to_quaternion(rot)
    assert (q[:, 3] >= 0).all()
    torch.testing.assert_close(se3.quaternion_to_rotation(q), rot, rtol=0, atol=1e-12)


def test_quaternion_known_answer():
    # 90 degrees about z: x axis goes to y axis; q = (0, 0, sin 45, cos 45) in x y z w order.
    q = torch.tensor([0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)], dtype=torch_dtype)
    rot = se3.quaternion_to_rotation(q)
    torch.testing.assert_close(rot @ torch.tensor([1.0, 0, 0], dtype=torch_dtype),
                               torch.tensor([0.0, 1, 0], dtype=torch_dtype), rtol=0, atol=1e-15)


def test_inverse_compose_and_adjoint():
    gen = torch.Generator().manual_seed(3)
    a, b = se3.exp(_random_tangent(8, gen)), se3.exp(_random_tangent(8, gen))
    eye = torch.eye(4, dtype=torch_dtype).expand(8, 4, 4)
    torch.testing.assert_close(se3.compose(a, se3.inverse(a)), eye, rtol=0, atol=1e-12)
    xi = _random_tangent(8, gen)
    lhs = a @ se3.exp(xi) @ se3.inverse(a)
    rhs = se3.exp((se3.adjoint(a) @ xi[..., None])[..., 0])
    torch.testing.assert_close(lhs, rhs, rtol=1e-10, atol=1e-10)
    # left update convention: retract(T, xi) = exp(xi) @ T
    torch.testing.assert_close(se3.retract(b, xi), se3.exp(xi) @ b)


def test_point_jacobian_matches_autograd():
    gen = torch.Generator().manual_seed(4)
    pts = torch.randn(10, 4, generator=gen, dtype=torch_dtype)

    def moved(xi):
        return (se3.exp(xi) @ pts[..., None])[..., :3, 0]

    jac = torch.func.jacfwd(moved)(torch.zeros(6, dtype=torch_dtype))  # (10, 3, 6)
    _assert_rel_close(se3.point_jacobian(pts), jac, 1e-12)


def _scene(n_edges: int = 5, n_pix: int = 40, seed: int = 5):
    gen = torch.Generator().manual_seed(seed)
    pose_i = se3.exp(_random_tangent(n_edges, gen, 0.1) * 0.3)
    pose_j = se3.exp(_random_tangent(n_edges, gen, 0.1) * 0.3)
    disp = 0.2 + torch.rand(n_edges, n_pix, generator=gen, dtype=torch_dtype) * 0.5
    pixels = torch.rand(n_pix, 2, generator=gen, dtype=torch_dtype) * torch.tensor([64.0, 48.0], dtype=torch_dtype)
    intr = torch.tensor([50.0, 50.0, 31.5, 23.5], dtype=torch_dtype)
    return pose_i, pose_j, disp, pixels, intr


def test_reprojection_known_answer_identity_and_translation():
    pose_i, _, disp, pixels, intr = _scene()
    same = projective.reproject(pose_i, pose_i, disp, pixels, intr, with_jacobians=False)
    torch.testing.assert_close(same.coords, pixels.expand_as(same.coords))
    # camera j moved by +b along x: a point at depth z moves by -f * b / z = -f * b * d in x
    eye = torch.eye(4, dtype=torch_dtype).expand(5, 4, 4).clone()
    moved = eye.clone()
    moved[:, 0, 3] = 0.3
    out = projective.reproject(eye, moved, disp, pixels, intr, with_jacobians=False)
    torch.testing.assert_close(out.coords[..., 0], pixels[:, 0] - 50.0 * 0.3 * disp)
    torch.testing.assert_close(out.coords[..., 1], pixels[:, 1].expand_as(disp))
    assert out.valid.all()


def test_reprojection_jacobians_match_autograd():
    pose_i, pose_j, disp, pixels, intr = _scene()
    out = projective.reproject(pose_i, pose_j, disp, pixels, intr)
    zero = torch.zeros(5, 6, dtype=torch_dtype)

    def coords(xi_i, xi_j, d, f):
        k = torch.stack([f, f, intr[2], intr[3]])
        return projective.reproject(se3.retract(pose_i, xi_i), se3.retract(pose_j, xi_j), d, pixels, k,
                                    with_jacobians=False).coords

    jac = torch.func.jacfwd(coords, argnums=(0, 1, 2, 3))(zero, zero, disp, intr[0])
    # jacfwd returns full (E,P,2, E,6) blocks; the analytic ones are the per-edge diagonal
    idx = torch.arange(5)
    _assert_rel_close(out.j_pose_i, jac[0][idx, :, :, idx])
    _assert_rel_close(out.j_pose_j, jac[1][idx, :, :, idx])
    jd = jac[2].reshape(5, 40, 2, 5 * 40)
    diag = jd[idx[:, None], torch.arange(40)[None, :], :, (idx[:, None] * 40 + torch.arange(40)[None, :])]
    _assert_rel_close(out.j_disp, diag)
    _assert_rel_close(out.j_focal, jac[3])


def test_focal_jacobian_holds_the_aspect_of_a_non_square_resize():
    """The working resize scales x and y differently (KITTI: 1.6 %): fx is the variable, fy = a fx follows."""
    pose_i, pose_j, disp, pixels, intr = _scene()
    aspect = 1.016
    intr = torch.stack([intr[0], intr[0] * aspect, intr[2], intr[3]])
    out = projective.reproject(pose_i, pose_j, disp, pixels, intr)

    def coords(fx):
        k = torch.stack([fx, fx * aspect, intr[2], intr[3]])
        return projective.reproject(pose_i, pose_j, disp, pixels, k, with_jacobians=False).coords

    _assert_rel_close(out.j_focal, torch.func.jacfwd(coords)(intr[0]))


def test_principal_point_jacobian_matches_autograd_and_leaves_the_others_as_they_were():
    """d coords / d (cx, cy) against jacfwd, on a non-square resize and an off-centre principal point; asking
    for it changes none of the other Jacobians."""
    pose_i, pose_j, disp, pixels, intr = _scene()
    intr = torch.stack([intr[0], intr[0] * 1.016, intr[2] - 3.0, intr[3] + 1.5])
    plain = projective.reproject(pose_i, pose_j, disp, pixels, intr)
    out = projective.reproject(pose_i, pose_j, disp, pixels, intr, principal_point=True)
    assert plain.j_principal is None and out.j_principal.shape == (5, 40, 2, 2)

    def coords(centre):
        k = torch.cat([intr[:2], centre])
        return projective.reproject(pose_i, pose_j, disp, pixels, k, with_jacobians=False).coords

    _assert_rel_close(out.j_principal, torch.func.jacfwd(coords)(intr[2:]))
    torch.testing.assert_close(out.j_pose_focal[..., :7], plain.j_pose_focal, rtol=0, atol=0)
    torch.testing.assert_close(out.coords, plain.coords, rtol=0, atol=0)


def test_reprojection_marks_points_behind_camera_invalid():
    eye = torch.eye(4, dtype=torch_dtype)[None]
    behind = eye.clone()
    behind[0, 2, 3] = 10.0  # camera j 10 units forward: a point at depth 2 is behind it
    out = projective.reproject(eye, behind, torch.tensor([[0.5]], dtype=torch_dtype),
                               torch.tensor([[3.0, 4.0]], dtype=torch_dtype),
                               torch.tensor([50.0, 50.0, 31.5, 23.5], dtype=torch_dtype), with_jacobians=False)
    assert not out.valid.any()


def test_shape_checks():
    with pytest.raises(ValueError):
        se3.exp(torch.zeros(5))
    pose_i, pose_j, disp, pixels, intr = _scene()
    with pytest.raises(ValueError):
        projective.reproject(pose_i[:2], pose_j, disp, pixels, intr)


def test_orthonormalize_projects_onto_rigid_transforms_and_keeps_rigid_ones():
    gen = torch.Generator().manual_seed(7)
    poses = se3.exp(torch.randn(5, 6, generator=gen, dtype=torch.float64))
    assert torch.allclose(se3.orthonormalize(poses), poses, atol=1e-12)
    bent = poses.clone()
    bent[:, :3, :3] += 1e-3 * torch.randn(5, 3, 3, generator=gen, dtype=torch.float64)
    fixed = se3.orthonormalize(bent)
    rot = fixed[:, :3, :3]
    assert torch.allclose(rot.transpose(1, 2) @ rot, torch.eye(3, dtype=torch.float64).expand(5, 3, 3), atol=1e-10)
    assert torch.allclose(torch.det(rot), torch.ones(5, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(fixed, poses, atol=1e-2) and torch.equal(fixed[:, :3, 3], bent[:, :3, 3])


def test_repeated_constant_velocity_prediction_stays_rigid():
    # T_{k+1} = T_k T_{k-1}^-1 T_k amplifies rounding off SO(3) about 2-3x per step (KITTI 07: det R reached
    # 1e28 after 22 keyframes); the frontend orthonormalizes each prediction
    step = se3.exp(torch.tensor([0.1, 0.0, 1.0, 0.02, 0.05, 0.01], dtype=torch.float64))
    raw = [torch.eye(4, dtype=torch.float64), step]
    kept = [torch.eye(4, dtype=torch.float64), step]
    for _ in range(40):
        raw.append(raw[-1] @ se3.inverse(raw[-2]) @ raw[-1])
        kept.append(se3.orthonormalize(kept[-1] @ se3.inverse(kept[-2]) @ kept[-1]))
    assert abs(float(torch.det(raw[-1][:3, :3])) - 1) > 1e-3  # the failure this guards against is real
    assert abs(float(torch.det(kept[-1][:3, :3])) - 1) < 1e-12


def test_flow_parts_take_the_rotation_out_and_measure_the_overlap():
    """Two keyframes at one spot turned 30 deg apart have a large induced flow, all of it the rotation's and none
    from depth; a sideways step moves pixels by its parallax alone, as the induced flow says; a turn of 80 deg in
    a 60 deg view leaves no overlap."""
    h, w, f = 24, 32, 28.0
    intr = torch.tensor([f, f, (w - 1) / 2, (h - 1) / 2], dtype=torch.float64)

    def pose(yaw_deg: float, x: float) -> torch.Tensor:
        out = torch.eye(4, dtype=torch.float64)
        out[:3, :3] = se3.so3_exp(torch.tensor([0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64))
        out[0, 3] = x
        return out

    poses = torch.stack([pose(0, 0), pose(30, 0), pose(0, 0.2), pose(80, 0)])
    disp = 1 / synthetic.room_depth(poses, intr, h, w)
    ii, jj = torch.tensor([0, 0, 0]), torch.tensor([1, 2, 3])
    induced = edges.induced_flow(poses, disp, intr, ii, jj)
    parts = edges.flow_parts(poses, disp, intr, ii, jj)
    torch.testing.assert_close(parts.induced, induced)
    assert float(parts.parallax[0]) < 1e-6 and float(parts.rotation[0]) == pytest.approx(float(induced[0]), rel=1e-6)
    assert float(induced[0]) > 10 and 0.4 < float(parts.overlap[0]) < 0.6  # half of the view turned away
    assert float(parts.parallax[1]) == pytest.approx(float(induced[1]), rel=1e-6) and float(parts.parallax[1]) > 1
    assert float(parts.rotation[1]) < 1e-9 and float(parts.overlap[2]) == 0.0
