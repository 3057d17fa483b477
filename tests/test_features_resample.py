"""The features service's resize and normalisation without torch, checked against torch itself.

``services.features.core.resample`` rebuilds ``F.interpolate(..., "bilinear", align_corners=False)`` (with and
without ``antialias``) as two weight matrices and ``F.normalize`` in numpy, so that the CPU path of features can
run without importing torch; these tests hold it to torch's outputs on random maps of every kind of size change.
"""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
F = torch.nn.functional

from services.features.core.resample import l2_normalise, resize_bilinear, resize_weights  # noqa: E402

SIZES = [  # (in, out): same, enlarge, shrink by a little, shrink by a lot, odd ratios, to and from one pixel
    ((48, 64), (48, 64)), ((27, 36), (48, 64)), ((384, 512), (378, 504)), ((384, 512), (98, 126)),
    ((37, 23), (11, 52)), ((5, 9), (1, 1)), ((1, 1), (4, 3)), ((7, 7), (3, 2)),
]


@pytest.mark.parametrize("antialias", [False, True])
@pytest.mark.parametrize("size_in,size_out", SIZES)
def test_resize_is_torch_interpolate(size_in, size_out, antialias):
    x = np.random.default_rng(0).standard_normal((5, *size_in)).astype(np.float32)
    ours = resize_bilinear(x, size_out, antialias=antialias)
    # float64 in torch: its index arithmetic is then in double as ours is (in float32 it rounds the source
    # positions of a 512-pixel row by ~5e-5 px, ~3e-4 on random data)
    ref = F.interpolate(torch.from_numpy(x).double()[None], size=size_out, mode="bilinear", align_corners=False,
                        antialias=antialias)[0].float().numpy()
    assert ours.shape == ref.shape == (5, *size_out) and ours.dtype == np.float32
    np.testing.assert_allclose(ours, ref, atol=2e-5, rtol=1e-5)


def test_weights_are_a_partition_of_unity_and_antialias_only_widens_a_shrink():
    for n_in, n_out in ((10, 3), (3, 10), (17, 17)):
        for aa in (False, True):
            w = resize_weights(n_in, n_out, aa)
            np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)  # a constant map stays constant
            assert (w >= 0).all()
    assert np.array_equal(resize_weights(3, 10, True), resize_weights(3, 10, False))  # enlarging: the same filter
    assert (resize_weights(10, 3, True) > 0).sum() > (resize_weights(10, 3, False) > 0).sum()  # shrinking: wider
    with pytest.raises(ValueError):
        resize_weights(0, 4)


def test_channels_beyond_opencvs_limit_resize_like_the_first():
    x = np.random.default_rng(1).standard_normal((768, 9, 13)).astype(np.float32)  # a ViT-B/14 map
    out = resize_bilinear(x, (16, 24))
    np.testing.assert_allclose(out[700], resize_bilinear(x[700:701], (16, 24))[0], atol=1e-6)


def test_l2_normalise_is_torch_normalize_zero_vectors_included():
    x = np.random.default_rng(2).standard_normal((6, 4, 5)).astype(np.float32)
    x[:, 0, 0] = 0.0
    np.testing.assert_allclose(l2_normalise(x, 0), F.normalize(torch.from_numpy(x), dim=0).numpy(), atol=1e-6)
    assert np.all(l2_normalise(x, 0)[:, 0, 0] == 0)
