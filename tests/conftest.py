"""Shared test set-up: the Taichi backend of the run (``--arch``), float64, a private colouring cache
(removed at the end of the run), and the check that keeps the ``backend`` marker honest.

``pytest --arch gpu`` (or ``VBD_TEST_ARCH=gpu``) runs every test on CUDA; where there is no CUDA GPU
they all skip with that reason. Taichi holds one backend per process, hence one option per run.

A test whose result depends on the backend, because it launches Taichi kernels in this process, carries
``@pytest.mark.backend`` (or its module sets ``pytestmark``); ``tests/test_backends.py`` re-runs exactly
those on CUDA. Every kernel launch is counted, and a test that launched one without the marker fails
and says so, so a new test cannot silently stay out of the CUDA run.

With ``--dist loadfile`` the test files go to the workers longest first, by the durations in
``tests/durations.json`` (``tools/mark_slow.py RUN.xml --write-durations tests/durations.json --overwrite``),
so that no worker ends alone on a long file; the files of a `SCOPE_GROUPS` group go to one worker, as one.
"""
import functools
import json
import os
import shutil
import tempfile
from pathlib import Path

import pytest

ARCHS = ("cpu", "gpu")
DURATIONS = Path(__file__).with_name("durations.json")     # written by tools/mark_slow.py --write-durations
# Files one worker runs together under --dist loadfile: each compiles the same large kernels (contact's sweep,
# detection and translation; the demo's contact scenes, the CUDA benchmark's pile and the sliver bunny's
# parallel sweep), which every worker that meets them compiles again (the fast subset: 3.5-5.6 s less wall
# time in three alternated pairs).
SCOPE_GROUPS = {"contact and scenes": ["tests/test_contact_sim.py", "tests/test_contact_refresh.py",
                                       "tests/test_contact_detection.py", "tests/test_contact_newton.py",
                                       "tests/test_translation_bodies.py", "tests/test_demo_scenes.py",
                                       "tests/test_demo_render.py", "tests/test_benchmark_cuda.py"]}
# The colouring / tetrahedralisation cache of this run: a folder of its own unless the caller chose one
# (xdist's workers inherit the controller's), removed when the process that made it ends its run.
OWN_CACHE = None
if "VBD_CACHE_DIR" not in os.environ:
    OWN_CACHE = os.environ["VBD_CACHE_DIR"] = tempfile.mkdtemp(prefix="vbd-cache-")


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
    config.stash[KERNEL_LAUNCHES] = KernelLaunches()
    if config.option.arch is None:
        config.option.arch = os.environ.get("VBD_TEST_ARCH") or "cpu"
        if config.option.arch not in ARCHS:
            raise pytest.UsageError(f"VBD_TEST_ARCH={config.option.arch!r} is not a backend; "
                                    f"set it to one of {', '.join(ARCHS)} or unset it")


def pytest_unconfigure(config):
    if OWN_CACHE is not None:
        shutil.rmtree(OWN_CACHE, ignore_errors=True)


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



class KernelLaunches:
    """Counts the Taichi kernel launches of this process (``ti.kernel`` calls, Taichi's own field copies
    such as ``to_numpy`` included), by wrapping the kernel class's call."""

    def __init__(self):
        from importlib import import_module

        from solver._ti import NAME, quick_kernel_calls

        quick_kernel_calls()            # first, so that the launches it makes are counted too
        kernel = import_module(f"{NAME}.lang.kernel_impl").Kernel
        launch = kernel.__call__
        self.count = 0

        @functools.wraps(launch)
        def counted(*args, **kwargs):
            self.count += 1
            return launch(*args, **kwargs)

        kernel.__call__ = counted


KERNEL_LAUNCHES = pytest.StashKey[KernelLaunches]()
LAUNCHES_BEFORE = pytest.StashKey[int]()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    item.stash[LAUNCHES_BEFORE] = item.config.stash[KERNEL_LAUNCHES].count
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Fail a passing test that launched kernels (in its set-up or its body) without the backend marker."""
    outcome = yield
    report = outcome.get_result()
    if call.when != "call" or not report.passed or item.get_closest_marker("backend"):
        return
    launched = item.config.stash[KERNEL_LAUNCHES].count - item.stash[LAUNCHES_BEFORE]
    if launched:
        report.outcome = "failed"
        report.longrepr = (f"{item.nodeid} launched {launched} Taichi kernels but is not marked backend, so the "
                           "CUDA run would leave it out: add @pytest.mark.backend (or pytestmark = "
                           "pytest.mark.backend in its module)")


@pytest.hookimpl(optionalhook=True)         # an xdist hook: pytest without xdist never calls it
def pytest_xdist_make_scheduler(config, log):
    """With --dist loadfile: hand out the test files longest first (xdist orders them by their number of
    tests, so a file of a few long tests, such as the homework grading, came last and one worker ran it alone
    while the other had finished), the files of each `SCOPE_GROUPS` group as one where the group's expected
    time fits in one worker's share of the run (on a machine of many workers, it would make the run longer)."""
    if config.getvalue("dist") != "loadfile" or not DURATIONS.is_file():
        return None
    from xdist.scheduler import LoadFileScheduling

    from tools.mark_slow import expected_seconds, fitting_groups, longest_first

    seconds = json.loads(DURATIONS.read_text())
    for name, files in SCOPE_GROUPS.items():      # a group's faster tests: those of its files
        seconds[name] = sum(seconds.get(f, 0.0) for f in files)

    class LongestFirst(LoadFileScheduling):
        group_of = {}           # file -> its group, for the groups that fit one worker's share

        def _split_scope(self, nodeid):
            scope = super()._split_scope(nodeid)
            return self.group_of.get(scope, scope)

        def schedule(self):
            collections = list(self.registered_collections.values())
            if self.collection is None and collections and all(c == collections[0] for c in collections):
                files = {}
                for nodeid in collections[0]:
                    files.setdefault(LoadFileScheduling._split_scope(self, nodeid), []).append(nodeid)
                self.group_of = fitting_groups(SCOPE_GROUPS, expected_seconds(files, seconds), len(self.nodes))
                scopes = {}
                for nodeid in collections[0]:
                    scopes.setdefault(self._split_scope(nodeid), []).append(nodeid)
                # xdist fills this queue in its own order; a key already present keeps its place
                for scope in longest_first(scopes, seconds):
                    self.workqueue[scope] = {}
            super().schedule()

    return LongestFirst(config, log)
