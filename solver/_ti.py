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


def light_allocation_tracebacks() -> bool:
    """Make allocating an ndarray cheaper, its debug record the same but for the source text: Taichi stores
    with every ndarray the Python stack that made it, for its error messages, formatted by ``traceback``,
    which reads the source line of every frame and checks every file on the stack for changes: little for
    one simulation, but it adds up over the thousands of arrays a test run allocates from deep stacks. The
    replacement writes the same ``File "...", line ..., in ...`` lines, leaving out the source lines under them.

    Returns whether it is in place (False where this Taichi allocates ndarrays otherwise, e.g. another
    version or Quadrants: nothing is changed then)."""
    import sys
    from importlib import import_module

    try:
        modules = [import_module(f"{NAME}.lang.{name}") for name in ("_ndarray", "matrix")]
        original = modules[0].get_traceback
    except (ImportError, AttributeError):
        return False
    if getattr(original, "light", False):
        return True

    def get_traceback(stacklevel=1):
        frame, lines = sys._getframe(stacklevel + 1), []
        while frame is not None:
            lines.append(f'  File "{frame.f_code.co_filename}", line {frame.f_lineno}, in {frame.f_code.co_name}\n')
            frame = frame.f_back
        return "".join(reversed(lines))

    get_traceback.light = True
    get_traceback.original = original
    for module in modules:
        if getattr(module, "get_traceback", None) is original:
            module.get_traceback = get_traceback
    return True


def memoise_source_positions() -> bool:
    """Make kernel compiles faster, with the same result, by memoising two lookups that Taichi's AST
    transform repeats each time a ``ti.func`` is inlined (at every call site, so a kernel that inlines
    the vertex solve once per colour repeats them hundreds of times):

    - the source of the function (``inspect.getsourcelines``, which tokenises it, and
      ``getsourcefile``): the same for the same function object;
    - the text it writes for every syntax node it visits (``ASTTransformerContext.get_pos_info``:
      "File ..., line ...", the source line and a ``^^^`` hint, wrapped by a new ``TextWrapper``): the
      same for the same source and node position, which together are its key.

    Returns whether the memos are in place (False where this Taichi lacks these functions, e.g. another
    version or Quadrants: nothing is changed then)."""
    from importlib import import_module

    try:
        kernel_impl = import_module(f"{NAME}.lang.kernel_impl")
        context = import_module(f"{NAME}.lang.ast.ast_transformer_utils").ASTTransformerContext
        source_lines, source_file, position = (kernel_impl.getsourcelines, kernel_impl.getsourcefile,
                                               context.get_pos_info)
    except (ImportError, AttributeError):
        return False
    if getattr(position, "memoised", False):
        return True
    lines_of, file_of, texts = {}, {}, {}

    def getsourcelines(func):
        try:
            found = lines_of.get(func)
        except TypeError:                           # unhashable: not memoised
            return source_lines(func)
        if found is None:
            found = lines_of[func] = source_lines(func)
        lines, first = found
        return list(lines), first

    def getsourcefile(func):
        try:
            found = file_of.get(func)
        except TypeError:
            return source_file(func)
        if found is None:
            found = file_of[func] = source_file(func)
        return found

    def get_pos_info(self, node):
        try:
            source = self.__dict__.get("_source_key")
            if source is None:
                source = self._source_key = (self.file, self.lineno_offset, self.func.func.__name__, tuple(self.src))
            body = getattr(node, "body", None)
            key = (source, type(node).__name__, node.lineno, node.end_lineno, node.col_offset, node.end_col_offset,
                   body[0].lineno if isinstance(body, list) and body else None)
        except (AttributeError, TypeError):         # not the context or node this memo was written for
            return position(self, node)
        text = texts.get(key)
        if text is None:
            text = texts[key] = position(self, node)
        return text

    get_pos_info.memoised = True
    get_pos_info.original = position
    getsourcelines.original = source_lines
    kernel_impl.getsourcelines, kernel_impl.getsourcefile = getsourcelines, getsourcefile
    context.get_pos_info = get_pos_info
    return True
