"""Shared test set-up: Taichi on the CPU in float64, and a private colouring cache folder."""
import os
import sys
import tempfile

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
os.environ.setdefault("VBD_CACHE_DIR", tempfile.mkdtemp(prefix="vbd-cache-"))


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    import solver

    solver.ensure_taichi("cpu")
