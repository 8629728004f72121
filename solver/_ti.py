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


def memoise_source_positions() -> bool:
    """Make kernel compiles faster, with the same result: memoise the text that Taichi's AST transform
    writes for every syntax node it visits (``ASTTransformerContext.get_pos_info``: "File ..., line ...",
    the source line and a ``^^^`` hint, each line wrapped by a new ``textwrap.TextWrapper``). It is made
    again each time a node is visited, and a ``ti.func`` is transformed anew at every call site, so a
    kernel that inlines the vertex solve once per colour builds the same texts hundreds of times: a
    quarter of the time of its first call (an 8-colour sweep of 38,400 tets: 2.4 s, 1.8 s memoised).

    The text depends only on the function's source (file, first line, lines) and the node's position
    and kind, which together are the key. Returns whether the memo is in place (False where this
    Taichi has no such method, e.g. another version or Quadrants: nothing is changed then)."""
    from importlib import import_module

    try:
        context = import_module(f"{NAME}.lang.ast.ast_transformer_utils").ASTTransformerContext
    except (ImportError, AttributeError):
        return False
    original = getattr(context, "get_pos_info", None)
    if original is None:
        return False
    if getattr(original, "memoised", False):
        return True
    texts = {}

    def get_pos_info(self, node):
        source = self.__dict__.get("_source_key")
        if source is None:
            source = self._source_key = (self.file, self.lineno_offset, self.func.func.__name__, tuple(self.src))
        body = getattr(node, "body", None)
        key = (source, type(node).__name__, node.lineno, node.end_lineno, node.col_offset, node.end_col_offset,
               body[0].lineno if isinstance(body, list) and body else None)
        text = texts.get(key)
        if text is None:
            text = texts[key] = original(self, node)
        return text

    get_pos_info.memoised = True
    get_pos_info.original = original
    context.get_pos_info = get_pos_info
    return True
