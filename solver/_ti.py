"""The kernel language: Taichi, or its maintained fork Quadrants where Taichi is not installed.

Quadrants (``pip install quadrants``) keeps Taichi's kernel API (``init``, ``kernel``, ``func``,
``field``, ``data_oriented``, ``ndarray``, ``loop_config``, ...) and has wheels for CPython 3.14,
which Taichi 1.7.4 has not; it has no GGUI (``ti.ui``), so the interactive window stays Taichi-only.
Taichi is used whenever it is importable. Modules write ``from solver._ti import ti`` where they
would write ``import taichi as ti``, and ask this module (not ``ti.lang`` internals) whether and
where the runtime is initialised, since that is where the two differ.
"""
import functools
import operator
import weakref

try:
    import taichi as ti
except ImportError:
    try:
        import quadrants as ti
    except ImportError:
        raise ImportError("neither taichi nor quadrants is installed; run "
                          "`pip install -r requirements.txt` with CPython 3.10-3.13") from None

import numpy as np

NAME = ti.__name__
# `quick_kernel_calls`: the launch contexts a kernel keeps, per set of arrays and templates, for calls
# with the same ones (a step calls most kernels with the same arrays; more sets than this start again).
REUSED_CONTEXTS = 4


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
    """Make kernel compiles faster, with the same result, by memoising three lookups that Taichi's AST
    transform repeats each time a ``ti.func`` is inlined (at every call site, so a kernel that inlines
    the vertex solve once per colour repeats them hundreds of times):

    - the source of the function (``inspect.getsourcelines``, which tokenises it, and
      ``getsourcefile``): the same for the same function object;
    - the text parsed from that source (``textwrap.fill`` of every line, by a new ``TextWrapper`` each
      time, and ``textwrap.dedent`` of the whole): the same for the same text;
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
    kernel_impl.textwrap = _MemoisedTextwrap(kernel_impl.textwrap)
    context.get_pos_info = get_pos_info
    return True


class _MemoisedTextwrap:
    """A stand-in for the ``textwrap`` module whose ``fill`` and ``dedent`` remember their results
    (`memoise_source_positions`); every other name is the module's own."""

    def __init__(self, module):
        self.module = module
        self.fill = functools.lru_cache(maxsize=1 << 14)(module.fill)
        self.dedent = functools.lru_cache(maxsize=1 << 10)(module.dedent)

    def __getattr__(self, name):
        return getattr(self.module, name)


def quick_kernel_calls() -> bool:
    """Make calling a kernel cheaper, with the same launches: Taichi's own call works out again at every
    launch, in Python, which compiled instance the arguments select (a key built from every argument's
    type, hashed), checks every argument against its annotation, finalises the fields, asks the compile
    cache for the compiled code and sets every argument through a chain of type tests: tens of
    microseconds a launch, and about ten more per array argument, where the kernel itself may take less
    (a VBD iteration of a classroom mesh passes ten arrays).

    The replacement keeps, per kernel, what it needs to launch again: how each argument is set (from the
    annotations, once), and per choice of compiled instance (the template arguments' values and each
    array's element type, dimensions and gradient, written as small integers cached on the array) the
    compiled code. numpy arrays are set as Taichi sets them (a C-contiguous array of an argument annotated
    without a vector or matrix element: its address, size and shape; Taichi's launcher copies it to and
    from a GPU). A call whose arguments it was not written for (keyword arguments, defaults left out,
    other numpy arrays, torch arrays, arrays with gradients, fields or compound values as templates, matrix
    or struct arguments or return values, autodiff, a kernel that prints, a tape or forward mode running)
    goes Taichi's own way, as does the first call of each instance, which compiles it; so do all calls
    after ``ti.init`` again until each instance has been met once more. Errors are Taichi's own.

    On the CPU, Taichi arrays are set by their host address, as numpy arrays are, and a kernel keeps the
    launch contexts of its last few sets of Taichi arrays and template values (REUSED_CONTEXTS): a call
    with the very same array objects (held by weak reference, so that a freed array's id met again is not
    taken for it) and equal templates sets only its scalars into that context and launches it again.
    Setting an array costs about a microsecond a launch, and a VBD iteration with contact passes 25
    (`python -m benchmarks.before_after --parts vbd contact`: a contact step of 8 cubes on a slab took
    0.79x the time, the same iterates). Calls with numpy arrays set everything each time (a numpy array
    can be reshaped in place).

    Returns whether it is in place (False where this Taichi launches kernels otherwise, e.g. another
    version or Quadrants: nothing is changed then)."""
    from importlib import import_module

    if NAME != "taichi" or tuple(getattr(ti, "__version__", ()))[:3] != (1, 7, 4):
        return False                # written against 1.7.4's `Kernel.__call__`, `launch_kernel` and mapper
    try:
        kernel_impl = import_module(f"{NAME}.lang.kernel_impl")
        impl = import_module(f"{NAME}.lang.impl")
        Kernel, Ndarray = kernel_impl.Kernel, import_module(f"{NAME}.lang._ndarray").Ndarray
        primitive_types = import_module(f"{NAME}.types.primitive_types")
        ndarray_type = import_module(f"{NAME}.types.ndarray_type").NdarrayType
        template = import_module(f"{NAME}.types").template
        data_type = import_module(f"{NAME}._lib").core.DataType
        none_mode, from_cpp = kernel_impl.AutodiffMode.NONE, kernel_impl.handle_exception_from_cpp
        is_signed, cook_dtype = kernel_impl.is_signed, kernel_impl.cook_dtype
        real_ids, integer_ids = primitive_types.real_type_ids, primitive_types.integer_type_ids
        Kernel.ensure_compiled, impl.PyTaichi.materialize       # what `call` uses besides the above
    except (ImportError, AttributeError):
        return False
    if getattr(Kernel, "quick_calls", None) is not None:
        return True
    taichi_call = Kernel.__call__
    ARRAY, SCALAR_ARRAY, FLOAT, INT, UINT, TEMPLATE = range(6)
    cpu_arch = ti.cpu
    template_types = (bool, int, float, str, type(None), data_type)
    signatures = {}                 # (element type, ndim) -> small int, so that keys hash quickly
    largest_index = np.iinfo(np.int32).max      # Taichi warns about larger arrays: its own call does that

    def plan_of(kernel):
        """((kind, (slot,)) per argument), or None where an annotation is of a kind not handled here."""
        plan, slot = [], 0
        for argument in kernel.arguments:
            annotation = argument.annotation
            if isinstance(annotation, template):
                plan.append((TEMPLATE, None))
                continue
            if isinstance(annotation, ndarray_type):
                scalars = annotation.dtype is None or id(annotation.dtype) in primitive_types.type_ids
                kind = SCALAR_ARRAY if scalars and not annotation.needs_grad else ARRAY
            elif id(annotation) in real_ids:
                kind = FLOAT
            elif id(annotation) in integer_ids:
                kind = INT if is_signed(cook_dtype(annotation)) else UINT
            else:
                return None
            plan.append((kind, (slot,)))
            slot += 1
        return tuple(plan)

    def nothing_to_materialise(runtime):
        """Whether `runtime.materialize()` would do nothing: no field declared since the last launch."""
        builder = impl._root_fb
        return (runtime.materialized and not runtime.global_vars and not runtime.grad_vars
                and not runtime.dual_vars and not runtime.matrix_fields and (builder.finalized or builder.empty)
                and all(b is builder for b in runtime.unfinalized_fields_builder))

    def readers_of(kernel):
        """(reader of each return value from a launched context), or None where a value is not a scalar."""
        readers = []
        for i, kind in enumerate(kernel.return_type or ()):
            if id(kind) in real_ids:
                readers.append(lambda context, index=(i,): context.get_struct_ret_float(index))
            elif id(kind) in integer_ids and is_signed(cook_dtype(kind)):
                readers.append(lambda context, index=(i,): context.get_struct_ret_int(index))
            elif id(kind) in integer_ids:
                readers.append(lambda context, index=(i,): context.get_struct_ret_uint(index))
            else:
                return None
        return tuple(readers)

    def call(self, *args, **kwargs):
        runtime = self.runtime
        memo = self.__dict__.get("_quick_calls")
        if memo is None or memo[0] is not runtime:
            readers = readers_of(self)
            plan = None if readers is None else plan_of(self)
            kinds = [] if plan is None else list(enumerate(plan))
            held = tuple(i for i, (kind, _) in kinds if kind in (ARRAY, SCALAR_ARRAY))
            chosen = tuple(i for i, (kind, _) in kinds if kind == TEMPLATE)
            scalars = tuple((i, kind, slot) for i, (kind, slot) in kinds if kind in (FLOAT, INT, UINT))
            reuse = {} if plan is not None and runtime.prog.config().arch == cpu_arch else None
            pick = picker(held + chosen)
            memo = self._quick_calls = (runtime, plan, readers, {}, held, chosen, scalars, reuse, pick)
        _, plan, readers, launches, held, chosen, scalars, reuse, pick = memo
        n_held = len(held)
        if (plan is None or kwargs or len(args) != len(plan) or self.autodiff_mode != none_mode or self.has_print
                or runtime.fwd_mode_manager or runtime.target_tape):
            return taichi_call(self, *args, **kwargs)
        if reuse is not None:
            picked = pick(args)
            known = reuse.get(tuple(map(id, picked)))
            if known is not None and same_objects(known, picked, n_held):
                if not nothing_to_materialise(runtime):
                    runtime.materialize()
                return launch(self, runtime, known[2], known[3], plan, scalars, args, readers, again=True, cpu=True)
        key = []
        for (kind, _), value in zip(plan, args):
            if kind == SCALAR_ARRAY and type(value) is np.ndarray:
                if not value.flags.c_contiguous or value.size > largest_index:
                    return taichi_call(self, *args, **kwargs)
                key.append(signatures.setdefault(("numpy", value.dtype, value.ndim), len(signatures)))
            elif kind in (ARRAY, SCALAR_ARRAY):
                if not isinstance(value, Ndarray) or value.grad is not None:
                    return taichi_call(self, *args, **kwargs)
                signature = value.__dict__.get("_launch_signature")
                if signature is None:
                    signature = value._launch_signature = signatures.setdefault(
                        (value.element_type, len(value.shape)), len(signatures))
                key.append(signature)
            elif kind == TEMPLATE:
                if not isinstance(value, template_types):
                    return taichi_call(self, *args, **kwargs)
                key.append((type(value), value))
        key = tuple(key)
        found = launches.get(key)
        if found is None:
            result = taichi_call(self, *args, **kwargs)       # compiles this instance on its first call
            prog = runtime.prog
            compiled = self.compiled_kernels[self.ensure_compiled(*args)]
            launches[key] = (compiled, prog.compile_kernel(prog.config(), prog.get_device_caps(), compiled))
            return result
        compiled, code = found
        if not nothing_to_materialise(runtime):
            runtime.materialize()
        context = compiled.make_launch_context()
        if reuse is not None and all(type(args[i]) is not np.ndarray for i in held):
            if len(reuse) >= REUSED_CONTEXTS:
                reuse.clear()
            picked = pick(args)
            reuse[tuple(map(id, picked))] = (tuple(map(weakref.ref, picked[:n_held])), picked[n_held:], code, context)
        return launch(self, runtime, code, context, plan, scalars, args, readers, again=False, cpu=reuse is not None)

    def host_array(runtime, value):
        """(address, bytes, shape) of a Taichi array on the CPU, cached on it. Set this way, a launch
        context stays right for the next launch: Taichi's CPU launcher turns an array set with
        `set_arg_ndarray` into its host address inside the context at launch, marks it as such, and at the
        next launch would pass the address of its allocation record in its place."""
        found = value.__dict__.get("_host_array")
        if found is None:
            found = value._host_array = (runtime.prog.get_ndarray_data_ptr_as_int(value.arr),
                                         value.arr.nelement() * value.arr.element_size(), tuple(value.shape))
        return found

    def picker(indices):
        """A function of a call's arguments returning the tuple of those at `indices`."""
        get = operator.itemgetter(*indices) if indices else (lambda args: ())
        return get if len(indices) != 1 else (lambda args: (args[indices[0]],))

    def same_objects(known, picked, n_held):
        """Whether a kept context (weak references to its arrays, its template values, ...) was set with
        the very arrays and equal templates of `picked` (the call's arrays, then its templates)."""
        if not all(map(operator.is_, [ref() for ref in known[0]], picked[:n_held])):
            return False
        return all(type(a) is type(b) and a == b for a, b in zip(picked[n_held:], known[1]))

    def launch(kernel, runtime, code, context, plan, scalars, args, readers, again, cpu):
        """Set the arguments into context (again: only the scalars, into a context set before with these
        arrays and templates), launch and return the kernel's values. cpu: Taichi arrays are set by their
        host address, as numpy arrays are (`host_array`)."""
        if not again:
            for (kind, slot), value in zip(plan, args):
                if kind == SCALAR_ARRAY and type(value) is np.ndarray:
                    context.set_arg_external_array_with_shape(slot, value.ctypes.data, value.nbytes, value.shape, 0)
                elif kind in (ARRAY, SCALAR_ARRAY) and cpu:
                    context.set_arg_external_array_with_shape(slot, *host_array(runtime, value), 0)
                elif kind in (ARRAY, SCALAR_ARRAY):
                    context.set_arg_ndarray(slot, value.arr)
        for i, kind, slot in scalars:
            value = args[i]
            if not isinstance(value, (int, float, np.integer, np.floating)) or (
                    kind != FLOAT and not isinstance(value, (int, np.integer))):
                return taichi_call(kernel, *args)
            elif kind == FLOAT:
                context.set_arg_float(slot, float(value))
            elif kind == INT:
                context.set_arg_int(slot, int(value))
            else:
                context.set_arg_uint(slot, int(value))
        try:
            runtime.prog.launch_kernel(code, context)
        except Exception as e:
            raise from_cpp(e) from None
        if not readers:
            return None
        runtime.prog.synchronize()
        values = [read(context) for read in readers]
        return values[0] if len(values) == 1 else values

    call.quick = True
    Kernel.quick_calls = taichi_call
    Kernel.__call__ = call
    return True
