"""The measurement objects of the fusion loop (fusion.measurements), the filters' routing of them by kind, and the
loop's own shape: no isinstance dispatch, no sensor named."""
import ast
import math
from pathlib import Path

import numpy as np

from fieldlog.fusion import earth, kf, measurements, methods
from fieldlog.fusion.still import ImuSums
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.dkf import DistributedKF
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.types import Epoch

ENGINE = Path(__file__).resolve().parents[1] / "fusion" / "engine.py"


def _moment(usable: bool, v_n=(10.0, 0.0, 0.0)) -> measurements.Moment:
    nav = NavState(0.0, math.radians(30.0), math.radians(104.0), 500.0, np.array(v_n, float),
                   earth.dcm_to_quat(earth.euler_to_dcm(math.radians(90.0), 0.0, 0.0)))
    ep = Epoch(1_000_000_000, nav.lat + 1e-7, nav.lon, nav.h, np.eye(3), 1, np.array(v_n, float), 0.01 * np.eye(3))
    return measurements.Moment(ep, usable, 0.0, ep.v_n if usable else np.full(3, np.nan), nav, np.zeros(3),
                               ImuSums(), 0.002, np.zeros(3), np.zeros(3), np.eye(15) * 1e-4)


def test_each_method_gets_its_list():
    assert methods.get("ins").measurements(FusionConfig()) == []
    ms = methods.get("kf").measurements(FusionConfig())
    assert [type(m).__name__ for m in ms] == ["FirstOf", "GpsVelocity", "GpsPosition"]
    assert [type(p).__name__ for p in ms[0].parts] == ["Stationary", "Odometer", "NonHolonomic"]
    assert [(m.kind, m.stage) for m in ms] == [("velocity", "aid"), ("velocity", "fix"), ("position", "fix")]
    bare = methods.get("dkf").measurements(FusionConfig.from_flat(nhc=False, zupt=False, odometer=False))
    assert [type(m).__name__ for m in bare] == ["GpsVelocity", "GpsPosition"]


def test_fix_measurements_only_at_a_usable_fix_and_nhc_only_when_moving():
    pos, vel = measurements.GpsPosition(np.zeros(3)), measurements.GpsVelocity(np.zeros(3), 100.0)
    nhc = measurements.NonHolonomic(0.1, 0.3, 0.5)
    at = _moment(True)
    z, H, R = pos.compute_matrices(at)
    assert len(z) == 3 and abs(z[1] + earth.principal_radii(at.nav.lat, at.nav.h)[0] * 1e-7) < 1e-6
    assert vel.compute_matrices(at) is not None and nhc.compute_matrices(at) is not None
    off = _moment(False)
    assert pos.compute_matrices(off) is None and vel.compute_matrices(off) is None
    assert nhc.compute_matrices(off) is not None  # an aid: the INS speed decides without a GPS velocity
    assert nhc.compute_matrices(_moment(True, (0.1, 0.0, 0.0))) is None  # slow: no constraint


def test_first_of_asks_in_order_and_refuses_mixed_kinds():
    class Fixed:
        kind, stage, receiver = "velocity", "aid", False

        def __init__(self, out):
            self.out, self.asked = out, 0

        def compute_matrices(self, m):
            self.asked += 1
            return self.out

    m = (np.zeros(1), np.zeros((1, 15)), np.eye(1))
    a, b = Fixed(None), Fixed(m)
    c = Fixed(m)
    assert measurements.FirstOf((a, b, c)).compute_matrices(_moment(True)) is m
    assert (a.asked, b.asked, c.asked) == (1, 1, 0)
    wrong = Fixed(m)
    wrong.kind = "position"
    try:
        measurements.FirstOf((a, wrong))
    except ValueError as e:
        assert "different kinds" in str(e)
    else:
        raise AssertionError("mixed kinds accepted")


def test_the_distributed_filter_routes_by_kind():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(15, 15))
    P0 = A @ A.T * 1e-2 + np.eye(15)
    H = np.zeros((3, 15))
    H[:, 3:6] = np.eye(3)
    m = (rng.normal(size=3), H, 0.1 * np.eye(3))
    for kind, moved, kept in (("velocity", 0, 1), ("position", 1, 0)):
        d = DistributedKF(P0, np.eye(12) * 1e-6)
        before = [(f.x.copy(), f.P.copy()) for f in d.locals]
        d.update_batch([kf.Observation(kind, m)])
        assert not np.array_equal(d.locals[moved].P, before[moved][1])
        assert np.array_equal(d.locals[kept].P, before[kept][1]) and np.array_equal(d.locals[kept].x, before[kept][0])


def test_the_loop_asks_no_isinstance_and_names_no_sensor():
    src = ENGINE.read_text()
    calls = {n.func.id for n in ast.walk(ast.parse(src)) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert "isinstance" not in calls
    for name in ("nhc", "zupt", "GpsPosition", "GpsVelocity", "NonHolonomic", "DistributedKF", "GpsErrorKF"):
        assert name not in src, name
    tree = ast.parse(src)
    documented = [n for n in ast.walk(tree) if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef))
                  and ast.get_docstring(n)]
    docs = {i for n in documented for i in range(n.body[0].lineno, n.body[0].end_lineno + 1)}
    code = [line for i, line in enumerate(src.splitlines(), 1)
            if i not in docs and line.strip() and not line.lstrip().startswith("#")]
    assert len(code) <= 300  # the loop's code, readable in one sitting (its numpydoc not counted)
