"""``fusion.median.median`` is ``np.median``'s float to the bit, and loads no ``numpy.ma``."""
import math
import subprocess
import sys

import numpy as np

from fieldlog.fusion.median import median


def test_median_is_numpys():
    """int64 host offsets near 1e18 ns (summed as floats), floats with ties, a NaN, odd and even counts, lists."""
    rng = np.random.default_rng(4)
    for n in (1, 2, 3, 8, 9, 120, 7141):
        for rep in range(10):
            a = 1_780_000_000 * 10**9 + rng.integers(-10**9, 10**9, n) if rep % 2 else rng.normal(size=n)
            if rep == 4:
                a = np.round(a, 1)
            if rep == 6:
                a[rng.integers(n)] = np.nan
            want = np.median(a)
            for given in (a, a.tolist()):
                got = median(given)
                assert type(got) is float and (got == want or (np.isnan(want) and math.isnan(got))), (n, rep)
    assert math.isnan(median([]))


def test_median_loads_no_masked_arrays():
    """np.median imports numpy.ma at its first call of a process; the engine's first block would pay it."""
    code = ("import sys, numpy as np; from fieldlog.fusion.median import median; median(np.arange(5.0)); "
            "median([1, 2]); print('numpy.ma' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
