"""Every method's solution on a 400 s figure8 drive (with and without smoothing, two GPS outages) and on a 400 s
urban drive (stops, tunnels) equals the reference in tests/data/engine_reference.npz to 1e-9 of each solution
column's scale (relative): a change of the engine's structure, or of its speed (compiled updates whose sums run in
another order than numpy's), must leave the rows alone to rounding (tests/engine_reference.py says how the
reference was made and how to regenerate it).

The counts (fixes used, epochs bridged, stationary updates, raised gammas) and the integer time stamps must be
equal. The simulated drives themselves are acquisition outputs: on the platform the reference was made on
(machine, numpy, the CPU features numpy dispatches to) their inputs' SHA-256 must match, bit for bit; elsewhere
the last bits of libm may differ, and the rows are still compared to 1e-9 of their scale."""
import numpy as np
import pytest

import engine_reference as er

RTOL = 1e-9


@pytest.fixture(scope="module")
def drives(simulated):
    return {name: simulated(scenario, er.DURATION_S, seed) for name, scenario, seed, _, _ in er.DRIVES}


def assert_to_scale(got: np.ndarray, want: np.ndarray, what: str) -> None:
    """got equals want (rows, columns...) to RTOL of each column's largest magnitude; integers exactly."""
    assert got.shape == want.shape, (what, got.shape, want.shape)
    if want.dtype.kind in "iub":
        assert np.array_equal(got, want), what
        return
    assert np.array_equal(np.isnan(got), np.isnan(want)), f"{what}: NaN rows differ"
    scale = np.nanmax(np.abs(want), axis=0) if want.size else 0.0
    err = np.abs(np.where(np.isnan(want), 0.0, got - want))
    bad = err > RTOL * np.maximum(scale, np.finfo(float).tiny)
    assert not bad.any(), f"{what}: {int(bad.sum())} values off by more than {RTOL:g} of their column's scale " \
                          f"(largest {float(np.nanmax(err / np.maximum(scale, np.finfo(float).tiny))):.3g})"


@pytest.mark.slow
def test_every_method_equals_the_reference(drives):
    ref = np.load(er.PATH)
    if str(ref["platform"]) == er.platform_key():
        for name, path in drives.items():
            assert er.input_digest(path) == str(ref[f"{name}/input"]), (
                f"the simulated {name} drive changed: the reference no longer fits the simulator; if the change "
                "is meant, regenerate it (tests/engine_reference.py)")
    labels = {k.rsplit("/", 1)[0] for k in ref.files if k.endswith("/counts")}
    done = set()
    for label, arrays in er.runs(drives):
        done.add(label)
        assert np.array_equal(arrays["counts"], ref[f"{label}/counts"]), (label, arrays["counts"])
        assert set(arrays) == {k.rsplit("/", 2)[-2] for k in ref.files if k.startswith(label + "/")
                               and k.endswith("/sha256")}, label
        for k, a in arrays.items():
            if k != "counts":
                assert_to_scale(a[::er.EVERY], ref[f"{label}/{k}"], f"{label}: {k}")
    assert done == labels


def test_the_comparison_sees_a_change_above_its_tolerance():
    want = np.column_stack([np.linspace(0.0, 1.0, 11), np.linspace(0.0, 1e-6, 11)])
    assert_to_scale(want * (1.0 + 0.5 * RTOL), want, "within")
    for col in range(2):
        got = want.copy()
        got[5, col] *= 1.0 + 4 * RTOL  # a small column is judged on its own scale, not the array's
        with pytest.raises(AssertionError):
            assert_to_scale(got, want, "off")
    t = np.arange(5, dtype=np.int64) * 10**18
    with pytest.raises(AssertionError):
        assert_to_scale(t + np.array([0, 0, 1, 0, 0]), t, "stamps")


def test_the_digest_sees_one_bit():
    a = np.linspace(0.0, 1.0, 11)
    b = a.copy()
    b[5] = np.nextafter(b[5], 2.0)
    assert er.digest(a) == er.digest(a.copy()) != er.digest(b)
    assert er.digest(a) != er.digest(a.astype(np.float32)) and er.digest(a) != er.digest(a.reshape(1, 11))
