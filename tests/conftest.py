"""Shared test set-up: the Taichi backend of the run (``--arch``), float64, a private colouring cache.

``pytest --arch gpu`` (or ``VBD_TEST_ARCH=gpu``) runs every test on CUDA; where there is no CUDA GPU
they all skip with that reason. Taichi holds one backend per process, hence one option per run.
"""
import os
import tempfile

import pytest

ARCHS = ("cpu", "gpu")
os.environ.setdefault("VBD_CACHE_DIR", tempfile.mkdtemp(prefix="vbd-cache-"))


def pytest_addoption(parser):
    parser.addoption("--arch", choices=ARCHS, default=None,
                     help="Taichi backend for the whole run: cpu, or gpu (CUDA). "
                          "Default: $VBD_TEST_ARCH, else cpu")


def _cuda_available() -> bool:
    from solver._ti import is_arch_supported, ti

    return is_arch_supported(ti.cuda)


@pytest.fixture(scope="session")
def cuda_present() -> bool:
    """Whether this Taichi build finds a CUDA driver and GPU (initialises nothing)."""
    return _cuda_available()


def pytest_configure(config):
    if config.option.arch is None:
        config.option.arch = os.environ.get("VBD_TEST_ARCH") or "cpu"
        if config.option.arch not in ARCHS:
            raise pytest.UsageError(f"VBD_TEST_ARCH={config.option.arch!r} is not a backend; "
                                    f"set it to one of {', '.join(ARCHS)} or unset it")


@pytest.fixture(scope="session")
def arch(request) -> str:
    """The run's backend: ``"cpu"`` or ``"gpu"``."""
    return request.config.option.arch


@pytest.fixture(scope="session", autouse=True)
def taichi_backend(arch):
    import solver

    if arch == "gpu" and not _cuda_available():
        pytest.skip("--arch gpu: no CUDA GPU on this machine")
    solver.ensure_taichi(arch)
