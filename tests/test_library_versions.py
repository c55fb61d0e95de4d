"""What keeps the project on every supported OpenCV, pymodbus and numpy (CI runs the suite on the oldest
and on the newest: these tests hold on each)."""

from __future__ import annotations

import re
import tomllib
from importlib import metadata
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def _requirements(*extras: str) -> dict[str, str]:
    """{distribution name, lower case: its requirement} of the project, and of the named optional extras."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    deps = project["dependencies"] + [d for e in extras for d in project["optional-dependencies"][e]]
    return {re.split(r"[<>=!~ ]", d, maxsplit=1)[0].lower(): d for d in deps}


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(x) for x in re.findall(r"\d+", text)[:3])


@pytest.mark.parametrize("dist", ["numpy", "opencv-python-headless", "pymodbus", "pyyaml", "pyserial", "matplotlib"])
def test_the_installed_version_is_within_the_supported_range(dist):
    spec = _requirements()[dist]
    installed = _version(metadata.version(dist))
    low = re.search(r">=\s*([\d.]+)", spec)
    high = re.search(r"<\s*([\d.]+)", spec)
    assert low and installed >= _version(low.group(1)), (dist, installed, spec)
    assert high and installed < _version(high.group(1)), (dist, installed, spec)


@pytest.mark.parametrize("leg", ["oldest", "newest"])
def test_each_ci_leg_pins_every_dependency_inside_its_range(leg):
    pins = {}
    for line in (REPO / ".ci" / f"constraints-{leg}.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, v = line.split("==")
            pins[name.strip().lower()] = _version(v)
    for dist, spec in _requirements("test").items():  # the test tools too: each leg installs ".[test]"
        assert dist in pins, f"{leg} leg does not pin {dist}"
        low = _version(re.search(r">=\s*([\d.]+)", spec).group(1))
        high = _version(re.search(r"<\s*([\d.]+)", spec).group(1))
        assert low <= pins[dist] < high, (leg, dist, pins[dist], spec)
        if leg == "oldest":  # the oldest leg is the lower bound itself
            assert pins[dist][: len(low)] == low, (dist, pins[dist], spec)


def test_only_the_driver_adapter_imports_pymodbus():
    importers = []
    for path in REPO.rglob("*.py"):
        if "tests" in path.relative_to(REPO).parts[:1]:
            continue
        if re.search(r"^\s*(from|import)\s+pymodbus", path.read_text(encoding="utf-8"), re.M):
            importers.append(path.relative_to(REPO).as_posix())
    assert importers == ["drivers/pneumatic_gripper/modbus.py"]


def test_bilinear_samples_lie_on_the_1_32_px_grid_on_every_opencv():
    """OpenCV 4 rounds INTER_LINEAR positions to 1/32 px, OpenCV 5 interpolates exactly: the silhouette's
    sampler (and the C kernel that reproduces it) rounds first, so both give 4's samples."""
    from selfview.measurement.silhouette import _remap

    img = np.tile(np.arange(10, dtype=np.float32) * 10, (4, 1))
    x = np.array([[0.51, 1.01, 2.3]], np.float32)
    got = _remap(img, x, np.ones_like(x))
    assert np.array_equal(got, np.array([[5.0, 10.0, 23.125]], np.float32))
    flat = _remap(img, x.ravel(), np.ones(3, np.float32))  # the 1-D path
    assert np.array_equal(flat, got.ravel())


def test_cv2_solve_takes_a_column_on_every_opencv():
    """The on-line update's normal equations: a (6, 1) right-hand side works on OpenCV 4 and 5 (5 refuses
    a 1-D array there), and gives numpy's answer."""
    rng = np.random.default_rng(1)
    J = rng.normal(size=(12, 6))
    r = rng.normal(size=12)
    ok, x = cv2.solve(J.T @ J, (J.T @ r)[:, None], flags=cv2.DECOMP_CHOLESKY)
    assert ok and x.shape == (6, 1)
    assert np.allclose(x.ravel(), np.linalg.solve(J.T @ J, J.T @ r), atol=1e-9)
