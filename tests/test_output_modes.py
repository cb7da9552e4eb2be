"""Outputs a lab can share: files written atomically (temporary file + rename) get the mode
``open()`` would give them, 0666 less the umask, not mkstemp's 0600."""

import os

import numpy as np
import pytest

from pipeline.h5io import atomic_h5, atomic_output, write_dataset


@pytest.fixture(params=[0o022, 0o002, 0o077, 0o027])
def umask(request):
    old = os.umask(request.param)
    yield request.param
    os.umask(old)


def mode(path):
    return os.stat(path).st_mode & 0o777


def test_atomic_h5_and_atomic_output_respect_the_umask(tmp_path, umask):
    with atomic_h5(tmp_path / "a.h5", stage="test") as f:
        write_dataset(f, "x", np.arange(3.0), "m")
    with atomic_output(tmp_path / "b.csv") as tmp:
        tmp.write_text("x_m\n1\n")
    open(tmp_path / "c.txt", "w").close()  # what open() gives
    assert mode(tmp_path / "a.h5") == mode(tmp_path / "b.csv") == mode(tmp_path / "c.txt") == 0o666 & ~umask


def test_failed_write_leaves_no_file(tmp_path):
    with pytest.raises(RuntimeError):
        with atomic_output(tmp_path / "b.csv") as tmp:
            tmp.write_text("half")
            raise RuntimeError("stage failed")
    assert list(tmp_path.iterdir()) == []
