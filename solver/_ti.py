"""The kernel language: Taichi, or its maintained fork Quadrants where Taichi is not installed.

Quadrants (``pip install quadrants``) keeps Taichi's kernel API (``init``, ``kernel``, ``func``,
``field``, ``data_oriented``, ``ndarray``, ``loop_config``, ...) and has wheels for CPython 3.14,
which Taichi 1.7.4 has not; it has no GGUI (``ti.ui``), so the interactive window stays Taichi-only.
Taichi is used whenever it is importable. Modules write ``from solver._ti import ti`` where they
would write ``import taichi as ti``, and ask this module (not ``ti.lang`` internals) whether and
where the runtime is initialised, since that is where the two differ.
"""
try:
    import taichi as ti
except ImportError:
    try:
        import quadrants as ti
    except ImportError:
        raise ImportError("neither taichi nor quadrants is installed; run "
                          "`pip install -r requirements.txt` with CPython 3.10-3.13") from None

NAME = ti.__name__


def runtime():
    """The object that stands for the running Taichi: ``ti.init`` (and ``ti.reset``) replace it, and
    free every field and ndarray made before, so an object holding arrays is usable only while this
    stays the same object."""
    from importlib import import_module

    return import_module(f"{NAME}.lang.impl").get_runtime()


def running_config():
    """The compile configuration of the running Taichi (``arch``, ``default_fp``, ``kernel_profiler``,
    ``cpu_max_num_threads``, ...), or None before ``init``.

    Taichi's runtime holds ``prog = None`` until ``ti.init``; Quadrants' ``prog`` property raises
    instead, so its private ``_prog`` is read.
    """
    prog = runtime()._prog if NAME == "quadrants" else runtime().prog
    return None if prog is None else prog.config()


def initialised_arch():
    """The arch the runtime was initialised on (``ti.cpu``, ``ti.cuda``, ...), or None before ``init``."""
    config = running_config()
    return None if config is None else config.arch


def is_arch_supported(arch) -> bool:
    """Whether this build and machine can run ``arch`` (e.g. ``ti.cuda``); initialises nothing."""
    from importlib import import_module

    return bool(import_module(f"{NAME}.lang.misc").is_arch_supported(arch))
