"""The compiled kernels (plain C, loaded with ctypes; no Python headers). Everything else is in pyproject.toml.

Built without floating-point contraction, so they give the same numbers to the bit on every machine."""
from setuptools import Extension, setup

FLAGS = ["-O2", "-ffp-contract=off", "-fno-math-errno"]
KERNELS = {"fieldlog.fusion._ins": "fusion/_ins.c", "fieldlog.fusion._cycles": "fusion/_cycles.c",
           "fieldlog.drive._chunks": "drive/_chunks.c",
           "fieldlog.tools.sim._sensors": "tools/sim/_sensors.c"}

# -O3 for the fusion kernels: the same IEEE operations in the same order (no contraction, no fast-math), the
# cycles' products vectorised across columns (the same sums, side by side) and the INS step scheduled better
OPTIMISED = {"fieldlog.fusion._cycles", "fieldlog.fusion._ins"}

setup(ext_modules=[Extension(name, [src], extra_compile_args=FLAGS + (["-O3"] if name in OPTIMISED else []))
                   for name, src in KERNELS.items()])
