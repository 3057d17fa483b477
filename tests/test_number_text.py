"""services.common.number_text: a table of numbers as text, checked against Python's own formatting."""
import numpy as np
import pytest

from services.common.number_text import format_rows


def test_rows_read_back_as_python_formats_them_and_offsets_slice_them():
    rng = np.random.default_rng(0)
    n = 2000
    x = rng.uniform(-1000, 1000, n) * rng.choice([1e-6, 1e-3, 1.0, 1e3], n)
    x[:6] = [0.0, -0.0000004, 0.5, -3.25, 1e-7, -0.4]
    ids = rng.integers(-5, 10**12, n)
    text, offsets = format_rows([x, ids], (6, 0))
    assert len(offsets) == n + 1 and offsets[-1] == len(text)
    rows = [text[a:b - 1].decode() for a, b in zip(offsets[:-1], offsets[1:])]
    expected = [f"{round(float(v), 6):.6f} {int(i)}".replace("-0.000000", "0.000000") for v, i in zip(x, ids)]
    assert rows == expected
    assert rows[:6:5] == ["0.000000 " + str(ids[0]), "-0.400000 " + str(ids[5])]
    # the text holds exactly what np.round holds, so a binary file of the rounded values agrees with it
    back = np.array(text.split(), float).reshape(n, 2)
    np.testing.assert_array_equal(back[:, 0], np.round(x, 6))


def test_integers_without_decimals_and_floats_rounded_to_integers():
    text, _ = format_rows([np.array([0, 7, -12, 10**18]), np.array([0.4, -0.6, 9.5, 1e15])], (0, 0))
    assert text.decode().split() == ["0", "0", "7", "-1", "-12", "10", "1000000000000000000", "1000000000000000"]


def test_an_empty_table_is_empty_text():
    text, offsets = format_rows([np.zeros(0), np.zeros(0, np.int64)], (3, 0))
    assert text == b"" and offsets.tolist() == [0]


@pytest.mark.parametrize("bad", [np.array([np.nan]), np.array([np.inf]), np.array([1e300])])
def test_values_fixed_point_cannot_hold_are_refused(bad):
    with pytest.raises(ValueError, match="fixed point"):
        format_rows([bad], (6,))


def test_columns_of_different_lengths_are_refused():
    with pytest.raises(ValueError, match="one length"):
        format_rows([np.zeros(3), np.zeros(4)], (0, 0))


@pytest.mark.parametrize("top", [2**32 - 1, 2**32])
def test_columns_either_side_of_32_bit_digits_read_as_python_formats_them(top):
    """Columns whose scaled values fit in 32 bits take narrower arithmetic: both sides of that line agree with
    Python's formatting, pixel coordinates to 1e-6 px among them."""
    rng = np.random.default_rng(1)
    ints = np.append(rng.integers(-top, top, 500), [top, -top, 0, 9, 10, 99, 100])
    pixels = np.append(rng.uniform(-0.5, 4095.5, 500), [top / 1e6, -top / 1e6, 0.0, 1e-6, 0.5, 9.999999, 10.0])
    text, _ = format_rows([ints, pixels], (0, 6))
    assert text.decode().split() == [s for i, v in zip(ints, pixels)
                                     for s in (str(int(i)), f"{round(float(v), 6):.6f}")]
