import math
import re

import numpy as np
import pytest

from fieldlog.acquire import calib
from fieldlog.acquire.calib import Calibration, SensorTriadCal, apply, default_calibration, load_calibration, to_counts


def _skewed_calibration(rng: np.random.Generator) -> Calibration:
    def triad(sens: float) -> SensorTriadCal:
        return SensorTriadCal(
            sensitivity=sens * rng.uniform(0.97, 1.03, 3),
            bias_V=rng.uniform(-0.2, 0.2, 3),
            misalignment=np.eye(3) + rng.normal(0.0, 0.01, (3, 3)),
        )

    return Calibration(gyro=triad(calib.GYRO_SENSITIVITY_SI), accel=triad(calib.ACCEL_SENSITIVITY_SI))


def test_defaults_follow_table_2():
    cal = default_calibration()
    counts = np.zeros((2, 6), np.int32)
    counts[0, 0] = 2**22  # 5 V on gyro x
    counts[1, 5] = round(2.0 / calib.LSB_V)  # 2 V on accel z
    omega_ib_b, f_b = apply(cal, counts)
    assert omega_ib_b[0, 0] == pytest.approx(math.radians(10.0), rel=1e-12)  # 500 mV/(deg/s)
    assert f_b[1, 2] == pytest.approx(calib.G0, rel=1e-6)  # 2000 mV/g
    assert np.count_nonzero(omega_ib_b) == 1 and np.count_nonzero(f_b) == 1
    # +-20 deg/s is the ADC full scale; +-2 g is well inside it.
    _, sat = to_counts(cal, np.array([[math.radians(19.9), 0, 0]]), np.array([[0, 0, 2 * calib.G0]]))
    assert sat.sum() == 0


def test_counts_si_counts_round_trip_is_exact():
    rng = np.random.default_rng(7)
    cal = _skewed_calibration(rng)
    counts = rng.integers(-(2**22), 2**22, size=(20_000, 6)).astype(np.int32)
    omega_ib_b, f_b = apply(cal, counts)
    back, sat = to_counts(cal, omega_ib_b, f_b)
    assert back.dtype == np.int32 and back.shape == counts.shape
    assert np.array_equal(back, counts)
    assert sat.tolist() == [0] * 6


def test_to_counts_rounds_to_nearest_and_clips():
    cal = default_calibration()
    lsb_rad_s = calib.LSB_V / calib.GYRO_SENSITIVITY_SI
    omega = np.array([[0.4 * lsb_rad_s, 0.6 * lsb_rad_s, -1.0], [0.0, 0.0, 1.0]])  # 1 rad/s >> 20 deg/s
    f_b = np.array([[0.0, 0.0, 9.8], [-100.0, 0.0, 9.8]])  # -100 m/s^2 -> -20.4 V
    counts, sat = to_counts(cal, omega, f_b)
    assert counts[0, :2].tolist() == [0, 1]
    assert counts[:, 2].tolist() == [calib.COUNTS_MIN, calib.COUNTS_MAX]
    assert counts[1, 3] == calib.COUNTS_MIN
    assert sat.tolist() == [0, 0, 2, 1, 0, 0]


def test_toml_round_trip_and_file(tmp_path):
    cal = _skewed_calibration(np.random.default_rng(3))
    text = cal.to_toml()
    back = Calibration.from_toml(text)
    for name in ("gyro", "accel"):
        for key in ("sensitivity", "bias_V", "misalignment"):
            assert np.array_equal(getattr(getattr(back, name), key), getattr(getattr(cal, name), key))
    path = tmp_path / "cal.toml"
    path.write_text(text)
    assert np.array_equal(load_calibration(path).gyro.misalignment, cal.gyro.misalignment)
    assert np.array_equal(load_calibration(str(path)).accel.bias_V, cal.accel.bias_V)


def test_default_toml_is_the_default_and_matches_the_docstring():
    default = default_calibration()
    for cal in (Calibration.from_toml(calib.default_toml()), load_calibration(None)):
        for name in ("gyro", "accel"):
            for key in ("sensitivity", "bias_V", "misalignment"):
                assert np.array_equal(getattr(getattr(cal, name), key), getattr(getattr(default, name), key))
    # The layout example in the module docstring must stay a valid, default calibration.
    example = "\n".join(
        line[4:] for line in calib.__doc__.split("TOML layout")[1].splitlines()[1:] if line.startswith("    ")
    )
    doc_cal = Calibration.from_toml(example)
    assert np.array_equal(doc_cal.gyro.sensitivity, default.gyro.sensitivity)
    assert np.array_equal(doc_cal.accel.sensitivity, default.accel.sensitivity)


def _default_dict() -> dict:
    import tomllib

    return tomllib.loads(calib.default_toml())


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d["gyro"].pop("bias_V"), "gyro.bias_V"),
        (lambda d: d.pop("accel"), "[accel]"),
        (lambda d: d["accel"].update(sensitivity=[1.0, 2.0]), "'sensitivity': expected shape (3,)"),
        (lambda d: d["gyro"].update(misalignment=[1.0, 0.0, 0.0]), "'misalignment': expected shape (3, 3)"),
        (lambda d: d["gyro"].update(bias_V=["a", 0.0, 0.0]), "'bias_V': not numeric"),
        (lambda d: d["gyro"].update(sensitivity=[1.0, 0.0, 1.0]), "'sensitivity': zero"),
        (
            lambda d: d["accel"].update(misalignment=[[1, 0, 0], [1, 0, 0], [0, 0, 1]]),
            "'misalignment': matrix is singular",
        ),
        (lambda d: d["accel"].update(scale=[1.0, 1.0, 1.0]), "'scale'"),
        (lambda d: d.update(magnetometer={}), "'magnetometer'"),
    ],
)
def test_bad_calibration_names_the_key(mutate, message):
    d = _default_dict()
    mutate(d)
    with pytest.raises(ValueError, match=re.escape(message)):
        Calibration.from_dict(d)


def test_invalid_toml_and_missing_file(tmp_path):
    with pytest.raises(ValueError, match="calibration is not valid TOML"):
        Calibration.from_toml("[gyro\nsensitivity = 1")
    with pytest.raises(ValueError, match=f"calibration file {tmp_path / 'nope.toml'} does not exist"):
        load_calibration(tmp_path / "nope.toml")
