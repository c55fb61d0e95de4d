"""The project is described in pyproject.toml; this file only declares its three optional C extensions
(the on-line per-frame step's kernels, see selfview/_native.py). ``optional=True``: where they cannot
be compiled (no C compiler), the install goes on and the package runs its pure-Python code."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("selfview._cnpu", ["selfview/_cnpu.c"], optional=True),
        Extension("selfview._ctrack", ["selfview/_ctrack.c"], optional=True),
        Extension("selfview._csil", ["selfview/_csil.c"], optional=True),
    ]
)
