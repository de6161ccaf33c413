"""The fusion methods as objects (``fusion.methods``): each method's name is spelled in that one module, and the
CLI, the viewer and the fusion loop take what they know of a method from its ``Method``."""
from __future__ import annotations

import ast
import subprocess
import sys

import numpy as np
import pytest

from fieldlog.fusion import methods, predictors
from fieldlog.fusion.config import FusionConfig
from test_imports import _modules


def _string_constants(path) -> set[str]:
    return {n.value for n in ast.walk(ast.parse(path.read_text(), str(path)))
            if isinstance(n, ast.Constant) and isinstance(n.value, str)}


def test_each_method_name_is_spelled_in_one_module():
    where: dict[str, list[str]] = {name: [] for name in methods.METHODS}
    for module, path in _modules().items():
        for s in _string_constants(path) & set(where):
            where[s].append(module)
    assert where["kf"], "the scan finds nothing: it reads no module"
    bad = {name: mods for name, mods in where.items() if mods != ["fieldlog.fusion.methods"]}
    assert not bad, f"method names spelled outside fusion.methods (use its Method objects): {bad}"


def test_the_registry_gives_the_cli_and_viewer_their_lists():
    from fieldlog.tools import cli

    assert tuple(cli.METHODS) == methods.METHODS == tuple(m.name for m in methods.REGISTRY.values())
    try:
        from fieldlog.replay.view import METHOD_COLORS
    except ImportError:
        pytest.skip("rerun-sdk is not installed (fieldlog[view])")
    assert METHOD_COLORS == {m.name: m.colour for m in methods.REGISTRY.values() if m.colour is not None}
    with pytest.raises(ValueError, match="unknown method 'kalman'"):
        methods.get("kalman")


def test_every_method_builds_its_filter_measurements_and_bridge():
    cfg = FusionConfig()
    P0, q = np.eye(15) * 1e-2, cfg.sensor.noise_psd()
    for m in methods.REGISTRY.values():
        f = m.filter(P0, q, cfg)
        assert np.allclose(f.covariance, P0), m.name
        assert bool(m.measurements(cfg)) == m.aided, m.name
        assert m.bridge is None or m.bridge.network in predictors.NETWORKS, m.name
        assert m.local_filters == bool(getattr(f, "has_locals", False)), m.name


def test_the_registry_imports_no_fusion_stack():
    """``fieldlog --help`` lists the methods; the registry must not pull numpy or the filters in to do it."""
    code = ("import sys, fieldlog.fusion.methods; "
            "print(sorted(m for m in sys.modules if m == 'numpy' or m.startswith('fieldlog.fusion.') "
            "and m != 'fieldlog.fusion.methods'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out
