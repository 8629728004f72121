"""The tests that depend on the backend on every backend present: the CPU run is the default run, and a
CPU run on a machine with a CUDA GPU also runs them once more on CUDA (``--arch gpu``).

Which tests those are is the ``backend`` marker: every test that launches Taichi kernels in the test
process carries it, and ``conftest.py`` fails one that launches kernels without it."""
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.backend
def test_the_run_uses_the_requested_backend(arch):
    from solver._ti import initialised_arch, ti

    assert initialised_arch() in {"cpu": (ti.x64, ti.arm64), "gpu": (ti.cuda,)}[arch]


def test_a_test_launching_kernels_without_the_marker_fails(tmp_path):
    for name in ("pytest.ini", "tests/conftest.py"):
        (tmp_path / Path(name).name).write_text((ROOT / name).read_text())
    (tmp_path / "test_launches.py").write_text(textwrap.dedent("""
        import numpy as np
        import pytest
        from solver._ti import ti

        def launch():
            x = ti.field(ti.f64, shape=3)
            return x.to_numpy()

        def test_unmarked():
            launch()

        @pytest.mark.backend
        def test_marked():
            launch()

        def test_numpy_only():
            np.zeros(3)
    """))
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_launches.py"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert "1 failed, 2 passed" in proc.stdout.splitlines()[-1], proc.stdout[-3000:]
    assert re.search(r"test_unmarked launched \d+ Taichi kernels but is not marked backend", proc.stdout), \
        proc.stdout[-3000:]


def test_a_run_removes_the_cache_folder_it_made_and_keeps_one_it_was_given(tmp_path):
    """The colouring cache of a test run is a temporary folder of its own, gone once the run ends (one was left
    in the temporary folder by every run); a folder named by VBD_CACHE_DIR is the caller's and stays."""
    (tmp_path / "conftest.py").write_text((ROOT / "tests/conftest.py").read_text())
    (tmp_path / "test_cache.py").write_text(textwrap.dedent("""
        import os

        def test_the_cache_folder_exists_during_the_run():
            assert os.path.isdir(os.environ["VBD_CACHE_DIR"])
    """))
    temporary, given = tmp_path / "tmp", tmp_path / "given"
    for folder in (temporary, given):
        folder.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "VBD_CACHE_DIR"}
    for extra in ({}, {"VBD_CACHE_DIR": str(given)}):
        proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_cache.py"],
                              cwd=tmp_path, capture_output=True, text=True, timeout=300,
                              env={**env, "PYTHONPATH": str(ROOT), "TMPDIR": str(temporary), **extra})
        assert proc.returncode == 0, proc.stdout[-3000:]
    assert not any(temporary.glob("vbd-cache-*")) and given.is_dir()


@pytest.mark.slow
def test_backend_tests_pass_on_cuda(arch, cuda_present):
    if arch != "cpu":
        pytest.skip("this run is the CUDA run")
    if not cuda_present:
        pytest.skip("no CUDA GPU on this machine: the backend tests ran on the CPU only")
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--arch", "gpu",
                           "-m", "backend"], cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stdout[-4000:]
    assert re.search(r"\b\d+ passed\b", proc.stdout.splitlines()[-1]), proc.stdout[-2000:]
