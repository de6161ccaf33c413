"""Every method's solution on a 400 s figure8 drive (with and without smoothing, two GPS outages) and on a 400 s
urban drive (stops, tunnels) equals the reference in tests/data/engine_reference.npz, bit for bit: a change of
the engine's structure, or of its speed, must leave the rows alone (tests/engine_reference.py says how the
reference was made and how to regenerate it).

Bit for bit where the floats can be: on the platform the reference was made on (machine, numpy, the CPU features
numpy dispatches to) every full array's SHA-256 must match. Elsewhere the last bits of libm and BLAS may differ;
there the sampled rows must agree to 1e-9 of their scale (the drives themselves then differ in their last bits)."""
import numpy as np
import pytest

import engine_reference as er


@pytest.fixture(scope="module")
def drives(simulated):
    return {name: simulated(scenario, er.DURATION_S, seed) for name, scenario, seed, _, _ in er.DRIVES}


@pytest.mark.slow
def test_every_method_equals_the_reference(drives):
    ref = np.load(er.PATH)
    exact = str(ref["platform"]) == er.platform_key()
    if exact:
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
            if k == "counts":
                continue
            rows = a[::er.EVERY]
            if exact:
                assert er.digest(a) == str(ref[f"{label}/{k}/sha256"]), f"{label}: {k} differs from the reference"
                assert np.array_equal(rows, ref[f"{label}/{k}"], equal_nan=True), (label, k)
            else:
                want = ref[f"{label}/{k}"]
                np.testing.assert_allclose(rows, want, rtol=1e-9, atol=1e-9 * float(np.nanmax(np.abs(want))),
                                           err_msg=f"{label}: {k}")
    assert done == labels


def test_the_digest_sees_one_bit():
    a = np.linspace(0.0, 1.0, 11)
    b = a.copy()
    b[5] = np.nextafter(b[5], 2.0)
    assert er.digest(a) == er.digest(a.copy()) != er.digest(b)
    assert er.digest(a) != er.digest(a.astype(np.float32)) and er.digest(a) != er.digest(a.reshape(1, 11))
