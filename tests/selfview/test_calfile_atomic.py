"""Saving a calibration replaces the file atomically and only with what reads back: a failure at any
point leaves the previous file as it was, and no temporary file behind."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from selfview.files.calfile import history_dir, load_calibration, save_calibration
from selfview.errors import CalibrationFileError
from tests.selfview.test_calfile import make_cal


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_a_failure_while_replacing_leaves_the_previous_file(tmp_path, rng, monkeypatch):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    before = p.read_bytes()
    real_replace = os.replace

    def failing_replace(src, dst, *a, **kw):
        if Path(dst) == p:  # the history copy goes through; the replacement of the file itself fails
            raise OSError(28, "No space left on device")
        return real_replace(src, dst, *a, **kw)

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(CalibrationFileError, match="(?i)no space left"):
        save_calibration(make_cal(rng, f=960.0), p)
    assert p.read_bytes() == before and load_calibration(p).camera.f == 950.0
    assert _leftovers(tmp_path) == []
    monkeypatch.setattr(os, "replace", real_replace)
    kept = save_calibration(make_cal(rng, f=970.0), p)
    assert load_calibration(p).camera.f == 970.0
    assert kept is not None and kept.parent == history_dir(p) and kept.read_bytes() == before


def test_a_failure_while_writing_leaves_the_previous_file(tmp_path, rng, monkeypatch):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    before = p.read_bytes()
    real_fsync = os.fsync
    calls = []

    def failing_fsync(fd):  # the disk fails after part of the new text went out
        calls.append(fd)
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", failing_fsync)
    with pytest.raises(CalibrationFileError, match="(?i)input/output error"):
        save_calibration(make_cal(rng, f=960.0), p, keep_history=False)
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert calls, "the writer never made its data durable"
    assert p.read_bytes() == before
    assert _leftovers(tmp_path) == []


def test_what_does_not_read_back_replaces_nothing(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    before = p.read_bytes()
    bad = make_cal(rng, f=960.0)
    bad.C_H_G = bad.C_H_G.copy()
    bad.C_H_G[:3, :3] *= 1.5  # not a rigid transform: the read-back refuses it
    with pytest.raises(CalibrationFileError, match="C_H_G"):
        save_calibration(bad, p, keep_history=False)
    assert p.read_bytes() == before
    assert _leftovers(tmp_path) == []
    with pytest.raises(CalibrationFileError, match="C_H_G"):  # nor creates a file that would not load
        save_calibration(bad, tmp_path / "new.yaml")
    assert not (tmp_path / "new.yaml").exists()
    assert np.isclose(load_calibration(p).camera.f, 950.0)

