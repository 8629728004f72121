"""Taichi initialisation and precision handling, shared by the solver and the demo renderer."""
import contextlib
import sys
import warnings
import weakref
from enum import Enum

from . import _ti
from ._ti import ti
from .errors import ConfigError, enum_value


class Precision(Enum):
    """Floating-point type of the simulation state."""

    FLOAT64 = "float64"
    FLOAT32 = "float32"

    @property
    def ti_dtype(self):
        return ti.f64 if self is Precision.FLOAT64 else ti.f32


def as_precision(value) -> Precision:
    """Accept a ``Precision`` or its name (``"float64"``/``"float32"``)."""
    return enum_value(Precision, value, "precision")


_warned_mismatch = set()


def _warn(message: str) -> None:
    """A UserWarning printed as one line (no source line under it)."""
    warnings.warn_explicit(message, UserWarning, filename="solver", lineno=0)


def running_on_cpu() -> bool:
    """Whether Taichi runs on the CPU backend (False before `ensure_taichi` and on CUDA)."""
    return _ti.initialised_arch() in (ti.x64, ti.arm64)


def ensure_taichi(arch=None) -> None:
    """Initialise Taichi once; later calls keep whatever backend is already running, with one
    warning when they ask for another one.

    ``arch`` is ``"cpu"``, ``"gpu"`` (CUDA, which supports float64) or None (whatever runs already,
    else the CPU). ``"gpu"`` falls back to the CPU with one warning when no CUDA GPU is available.
    """
    if arch not in (None, "cpu", "gpu"):
        raise ConfigError(f"unknown arch {arch!r}; use 'cpu' or 'gpu'")
    _ti.memoise_source_positions()
    _ti.light_allocation_tracebacks()
    _ti.quick_kernel_calls()
    running = _ti.initialised_arch()
    if running is not None and arch is not None:
        on_cpu = running_on_cpu()
        if (arch == "gpu") == on_cpu and arch not in _warned_mismatch:
            _warned_mismatch.add(arch)
            name = "the CPU" if on_cpu else "the GPU"
            _warn(f"arch={arch!r} was asked for, but Taichi already runs on {name} in this process; "
                  f"keeping {name} (start a new process to change the backend)")
    if running is not None:
        return
    arch = arch or "cpu"
    if arch == "gpu":
        ti.set_logging_level(ti.ERROR)   # keep the CUDA probe quiet; our own warning says what happened
        if not _ti.is_arch_supported(ti.cuda):
            _warn("no CUDA GPU is available here; running on the CPU instead")
            arch = "cpu"
    with contextlib.redirect_stdout(sys.stderr):    # "[Taichi] Starting on arch=...": not program output
        ti.init(arch=ti.cpu if arch == "cpu" else ti.cuda, default_fp=ti.f64, log_level=ti.WARN)


class RuntimeCache:
    """A cache of objects that hold Taichi arrays (a mesh's adjacency on the device, a Newton solver's
    buffers), shared by the simulations of one Taichi runtime. `ti.init` frees every array made
    before it, so `get()` hands out a new, empty store once Taichi has been initialised again.

    make: the store's type (`dict`, `collections.OrderedDict`, `weakref.WeakKeyDictionary`).
    """

    def __init__(self, make=dict):
        self._make = make
        self._runtime = None        # weak reference to the runtime the store belongs to
        self._store = make()

    def get(self):
        """The store of the running Taichi (`_ti.runtime`)."""
        running = _ti.runtime()
        if self._runtime is None or self._runtime() is not running:
            self._store = self._make()
            self._runtime = weakref.ref(running)
        return self._store
