"""The C reader (readers/c) against the Python engine: `make -C readers/c test`.

Needs a C compiler and the HDF5 development package (`h5cc`); the make test writes
LUTs of every kind with NaN nodes and out-of-range heights, compares C and Python
to 1e-9 mm and runs damaged and foreign files under AddressSanitizer.
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

READER = Path(__file__).resolve().parents[2] / "readers" / "c"


@pytest.mark.slow
def test_make_test_of_the_c_reader():
    if shutil.which("h5cc") is None or shutil.which("make") is None:
        pytest.fail("h5cc or make not found: install the HDF5 development package (apt-get install libhdf5-dev)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(READER.parents[1]), os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run(["make", "-C", str(READER), "test", f"PYTHON={sys.executable}"], capture_output=True,
                         text=True, env=env, timeout=900)
    if res.returncode != 0:
        pytest.fail(f"make -C readers/c test failed ({res.returncode}):\n{res.stdout[-6000:]}\n{res.stderr[-6000:]}")
    assert "all C reader checks passed" in res.stdout
