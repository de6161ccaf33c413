"""``acquire.rows.dot``: a product of many rows by a small matrix, in blocks, keeps numpy's bits."""
import numpy as np
import pytest

from fieldlog.acquire import rows


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a).view(np.uint64)


@pytest.mark.parametrize("k, p", [(3, 3), (2, 2), (6, 3), (1, 2), (3, 1)])
def test_dot_keeps_numpys_bits_across_block_edges(k, p):
    rng = np.random.default_rng(k * 10 + p)
    step = max(4, rows.SERIAL_MULADDS // (k * p))
    m = rng.normal(size=(k, p))
    # a last block of 8, 16 or 32 rows: the sizes OpenBLAS may hand to its small-matrix kernels
    for n in (0, 1, 2, 5, step - 1, step, step + 1, step + 2, 3 * step + 1, 5 * step + 7, 2 * step + 8,
              2 * step + 16, 2 * step + 32):
        x = rng.normal(size=(n, k)) * 10.0 ** rng.uniform(-6, 6, size=(1, k))
        want = np.dot(x, m)
        got = rows.dot(x, m)
        assert got.shape == (n, p) and got.flags.c_contiguous
        assert np.array_equal(_bits(got), _bits(want)), (n, k, p)
        assert np.array_equal(_bits(got), _bits(x @ m)), (n, k, p)


def test_dot_keeps_the_bits_of_strided_operands():
    """A column slice of a wider array and a transposed matrix, as the calibration and the simulator pass them."""
    rng = np.random.default_rng(5)
    step = rows.SERIAL_MULADDS // 9
    wide = rng.normal(size=(4 * step + 1, 6))
    m = rng.normal(size=(3, 3))
    for x in (wide[:, :3], wide[:, 3:], wide[::2, 1:4]):
        for mm in (m, m.T, np.linalg.inv(m).T):
            assert np.array_equal(_bits(rows.dot(x, mm)), _bits(np.dot(x, mm)))


def test_dot_refuses_mismatched_shapes():
    with pytest.raises(ValueError, match="rows.dot"):
        rows.dot(np.zeros((4, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="rows.dot"):
        rows.dot(np.zeros(3), np.zeros((3, 3)))


def test_blocks_cover_the_rows_in_order_and_leave_no_row_alone():
    for n, step in [(0, 8), (1, 8), (2, 8), (8, 8), (9, 8), (10, 8), (17, 8), (100, 3), (5, 1000)]:
        b = rows.blocks(n, step)
        starts, ends = [i for i, _ in b], [j for _, j in b]
        assert (starts == [0] + ends[:-1] and ends[-1] == n) if n else b == []
        assert all(j - i <= max(4, step) for i, j in b)
        assert n == 1 or all(j - i > 1 for i, j in b)
