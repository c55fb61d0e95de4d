"""The project is described in pyproject.toml; this file only declares the optional C kernel of the
silhouette fit (see selfview/measurement/_native.py). ``optional=True``: without a C compiler the install goes on
and the package runs its numpy code."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("selfview.measurement._csil", ["selfview/measurement/_csil.c"], optional=True)])
