"""The solver and renderer tests on every backend present: the CPU run is the default run, and a
CPU run on a machine with a CUDA GPU also runs them once more on CUDA (``--arch gpu``)."""
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SOLVER_TESTS = ["tests/test_material.py", "tests/test_coloring.py", "tests/test_mesh.py", "tests/test_newton.py",
                "tests/test_simulation.py", "tests/test_demo_render.py"]


def test_the_run_uses_the_requested_backend(arch):
    from solver._ti import initialised_arch, ti

    assert initialised_arch() in {"cpu": (ti.x64, ti.arm64), "gpu": (ti.cuda,)}[arch]


@pytest.mark.slow
def test_solver_tests_pass_on_cuda(arch, cuda_present):
    if arch != "cpu":
        pytest.skip("this run is the CUDA run")
    if not cuda_present:
        pytest.skip("no CUDA GPU on this machine: the solver tests ran on the CPU only")
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--arch", "gpu",
                           *SOLVER_TESTS], cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stdout[-4000:]
    assert re.search(r"\b\d+ passed\b", proc.stdout.splitlines()[-1]), proc.stdout[-2000:]
