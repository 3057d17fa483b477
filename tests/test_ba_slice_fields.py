"""A field of every edge joined from slices (services/ba/core/slice_fields.py)."""
import torch

from services.ba.core.slice_fields import join_slice


def test_a_field_formed_in_slices_holds_each_slices_part_and_nothing_of_the_last_evaluation():
    """``join_slice`` joins a slice's field into the field of every edge, reusing the last evaluation's: a kernel
    mask that is None (nowhere) in a slice is False there even where the last evaluation's was True; a broadcast
    part stays a view; a part that is the field's own slice (an ARK cache edge kept) is left as it is."""
    edges = [slice(0, 1), slice(1, 2)]

    def joined(parts, whole=None):
        for part, at in zip(parts, edges):
            whole = join_slice(whole, part, at, 2)
        return whole

    first = joined([torch.tensor([[True, False]]), torch.tensor([[False, True]])])
    assert first.tolist() == [[True, False], [False, True]]
    again = joined([None, torch.tensor([[True, True]])], first)
    assert again is first and again.tolist() == [[False, False], [True, True]]
    assert joined([None, torch.tensor([[True, False]])]).tolist() == [[False, False], [True, False]]
    assert joined([None, None]) is None
    one = torch.full((1, 1), 2.0).expand(1, 3)
    view = joined([one, one])
    assert view.shape == (2, 3) and view.stride() == (0, 0) and view.tolist() == [[2.0] * 3] * 2
    values = torch.arange(6.0).view(2, 3)
    kept = joined([values[0:1], torch.tensor([[9.0, 9.0, 9.0]])], values)
    assert kept is values and kept.tolist() == [[0.0, 1.0, 2.0], [9.0, 9.0, 9.0]]

