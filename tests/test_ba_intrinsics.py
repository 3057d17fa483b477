"""The camera model BA refines: a step's projection onto the focal's bounds and the principal point's range."""
import torch

from services.ba.core import intrinsics
from services.ba.core.params import BAParams

GRID_HW = (24, 32)
START = torch.tensor([20.0, 22.0, 15.5, 11.5], dtype=torch.float64)  # fy/fx = 1.1, principal point at the centre


def _params(principal: bool, range_: float = 0.15) -> BAParams:
    return BAParams(optimise_focal=True, optimise_principal_point=principal, principal_point_range=range_)


def test_focal_step_keeps_the_aspect_and_stops_at_its_bound():
    step = torch.tensor(5.0, dtype=torch.float64)
    moved = intrinsics.apply_step(START, step, torch.zeros(2), GRID_HW, _params(False), focal_bounds=(10.0, 23.0))
    assert float(moved[0]) == 23.0
    assert abs(float(moved[1] / moved[0]) - 1.1) < 1e-12
    # held principal point: a step in it is ignored
    held = intrinsics.apply_step(START, step * 0, torch.tensor([3.0, -2.0]), GRID_HW, _params(False))
    assert torch.equal(held, START)


def test_principal_point_moves_within_its_range_about_the_grid_centre():
    params = _params(True, range_=0.1)  # 3.2 px in x and 2.4 px in y either side of (15.5, 11.5)
    small = intrinsics.apply_step(START, torch.tensor(0.0), torch.tensor([1.0, -0.5]), GRID_HW, params)
    torch.testing.assert_close(small[2:], START[2:] + torch.tensor([1.0, -0.5], dtype=torch.float64))
    large = intrinsics.apply_step(START, torch.tensor(0.0), torch.tensor([10.0, -10.0]), GRID_HW, params)
    torch.testing.assert_close(large[2:], torch.tensor([15.5 + 3.2, 11.5 - 2.4], dtype=torch.float64))


def test_free_indices_and_the_prior_follow_what_is_estimated():
    assert intrinsics.free_camera_indices(3, _params(False), None).tolist() == list(range(6, 18)) + [18]
    assert intrinsics.free_camera_indices(3, _params(True), None).tolist() == list(range(6, 18)) + [18, 19, 20]
    assert intrinsics.free_camera_indices(3, BAParams(), None).tolist() == list(range(6, 18))
    assert intrinsics.principal_prior(START, START[2:], _params(False)) is None
    guess = START[2:] - torch.tensor([2.0, -1.0], dtype=torch.float64)
    prior = intrinsics.principal_prior(START, guess, BAParams(optimise_focal=True, optimise_principal_point=True,
                                                                 principal_point_sigma=0.5), n_kf=3)
    assert prior.indices.tolist() == [19, 20]  # after the 3 poses' 18 columns and the focal
    torch.testing.assert_close(prior.gradient, torch.tensor([-8.0, 4.0], dtype=torch.float64))
    assert prior.energy == 0.5 * 4.0 * (4.0 + 1.0)
