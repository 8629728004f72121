"""solver._ti: Taichi where it is installed, else its fork Quadrants, and the runtime queries that differ."""
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from solver import _ti


def run(code):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_taichi_is_preferred_and_the_module_is_the_real_one():
    expected = "taichi" if importlib.util.find_spec("taichi") else "quadrants"
    assert _ti.NAME == expected and _ti.ti is sys.modules[expected]


def test_initialised_arch_is_none_before_init_and_the_arch_after():
    out = run("from solver._ti import ti, initialised_arch\n"
              "assert initialised_arch() is None\n"
              "ti.init(arch=ti.cpu)\n"
              "print(initialised_arch() in (ti.x64, ti.arm64))\n")
    assert out.returncode == 0 and out.stdout.strip().splitlines()[-1] == "True", out.stderr[-2000:]


def test_without_taichi_it_falls_back_to_quadrants_or_says_what_to_install():
    # `import solver` itself imports taichi, so the shim is loaded on its own; a None entry in
    # sys.modules makes `import taichi` raise ImportError as on a machine without it
    out = run("import importlib.util, sys\nsys.modules['taichi'] = None\n"
              f"spec = importlib.util.spec_from_file_location('shim', {_ti.__file__!r})\n"
              "shim = importlib.util.module_from_spec(spec)\n"
              "try:\n    spec.loader.exec_module(shim)\nexcept ImportError as e:\n    print('ImportError:', e)\n"
              "else:\n    print('fell back to', shim.NAME)\n")
    assert out.returncode == 0, out.stderr[-2000:]
    last = out.stdout.strip().splitlines()[-1]
    if importlib.util.find_spec("quadrants"):
        assert last == "fell back to quadrants"
    else:
        assert last.startswith("ImportError: neither taichi nor quadrants is installed; run `pip install")


def test_memoised_textwrap_gives_taichi_the_source_text_it_would_make():
    """The AST transform parses fill(line, tabsize=4, width=9999) of every source line and the dedent of
    their join: the memoised stand-in returns the module's own results, from its memo the second time."""
    import textwrap
    from importlib import import_module

    import solver

    solver.ensure_taichi()
    wrap = import_module(f"{_ti.NAME}.lang.kernel_impl").textwrap
    if wrap is textwrap:
        pytest.skip(f"{_ti.NAME}'s kernel_impl is not memoised")
    lines = (Path(_ti.__file__).parent / "vbd" / "vertex_solve.py").read_text().splitlines()
    lines += ["\tx = 1  # a tab", "    y = [1,\t2]", ""]
    for _ in range(2):
        assert [wrap.fill(line, tabsize=4, width=9999) for line in lines] == [
            textwrap.fill(line, tabsize=4, width=9999) for line in lines]
        assert wrap.dedent("\n".join(lines[-3:])) == textwrap.dedent("\n".join(lines[-3:]))
    assert wrap.fill.cache_info().hits >= len(set(lines)) and wrap.indent is textwrap.indent


@pytest.mark.backend
def test_memoised_source_positions_are_the_texts_taichi_writes(monkeypatch):
    from importlib import import_module

    import solver

    solver.ensure_taichi()
    context = import_module(f"{_ti.NAME}.lang.ast.ast_transformer_utils").ASTTransformerContext
    memo = context.get_pos_info
    if not getattr(memo, "memoised", False):
        pytest.skip(f"{_ti.NAME} has no ASTTransformerContext.get_pos_info: nothing is memoised")
    compared = []

    def both(self, node):
        text = memo(self, node)
        compared.append(text == memo.original(self, node))
        return text

    monkeypatch.setattr(context, "get_pos_info", both)

    @_ti.ti.func
    def twice(x, y):
        for k in range(3):
            if x[k] > y[k]:
                x[k] = (y[k]
                        + 1.0)
        return x

    @_ti.ti.kernel
    def inlines_twice(a: _ti.ti.types.ndarray()) -> _ti.ti.f64:
        u = twice(a[0], a[1])
        v = twice(a[1], a[0])
        return u.sum() + v.sum()

    a = _ti.ti.Vector.ndarray(3, _ti.ti.f64, 2)
    a.from_numpy(np.array([[1.0, 5.0, 2.0], [3.0, 4.0, 0.5]]))
    assert inlines_twice(a) == pytest.approx((1.0 + 5.0 + 1.5) + (2.0 + 4.0 + 0.5))
    assert len(compared) > 20 and all(compared)
    kernel_impl = import_module(f"{_ti.NAME}.lang.kernel_impl")
    assert kernel_impl.getsourcelines(twice.func.func) == kernel_impl.getsourcelines.original(twice.func.func)

    @_ti.ti.kernel
    def misspelt(a: _ti.ti.types.ndarray()):
        a[0] = undefined_name    # noqa: F821

    with pytest.raises(Exception, match=r'(?s)line \d+, in misspelt:\n\s+a\[0\] = undefined_name.*\^+'):
        misspelt(a)


def test_light_allocation_tracebacks_keep_taichis_frame_lines():
    """Every ndarray Taichi allocates records the stack that made it; the light record has the same
    "File ..., line ..., in ..." lines as Taichi's own, in the same order, without the source text."""
    from importlib import import_module

    import solver

    solver.ensure_taichi()
    light = import_module(f"{_ti.NAME}.lang._ndarray").get_traceback
    if not getattr(light, "light", False):
        pytest.skip(f"{_ti.NAME} records ndarray allocations otherwise: nothing is replaced")

    def allocate():                 # stands for Ndarray.__init__: stacklevel=1 leaves it out
        return light(), light.original()

    ours, taichis = allocate()
    assert ours.startswith('  File "')
    assert ours.endswith(", in test_light_allocation_tracebacks_keep_taichis_frame_lines\n")
    assert ours.splitlines() == [line for line in taichis.splitlines() if line.startswith('  File "')]
    assert _ti.light_allocation_tracebacks() and import_module(f"{_ti.NAME}.lang.matrix").get_traceback is light


def _quick_or_skip():
    import solver

    solver.ensure_taichi()
    if not _ti.quick_kernel_calls():
        pytest.skip(f"{_ti.NAME} launches kernels otherwise: nothing is replaced")
    from importlib import import_module

    return import_module(f"{_ti.NAME}.lang.kernel_impl").Kernel


@_ti.ti.kernel
def _mixed(x: _ti.ti.types.ndarray(), v: _ti.ti.types.ndarray(), s: _ti.ti.f64, n: _ti.ti.i32,
           dtype: _ti.ti.template(), k: _ti.ti.template()) -> (_ti.ti.f64, _ti.ti.i32):
    total = _ti.ti.cast(0, _ti.ti.f64)
    for i in range(n):
        x[i] = _ti.ti.cast(s * i + k, dtype) / 3
        v[i] = v[i] * s + _ti.ti.Vector([i, k, 1.0 / 3])
        total += x[i] + v[i].sum()
    return total, n * k


@pytest.mark.backend
def test_quick_calls_launch_what_taichis_own_call_launches(monkeypatch):
    """The quick call sets every argument as Taichi's own does (arrays of scalars and of vectors, floats,
    ints, templates selecting the instance) and returns the same values: the same arrays after the same
    calls made either way."""
    Kernel = _quick_or_skip()
    rng = np.random.default_rng(3)
    v0 = rng.standard_normal((8, 3))
    results = {}
    for way in ("taichi", "quick"):
        x = _ti.ti.ndarray(_ti.ti.f64, 8)
        v = _ti.ti.Vector.ndarray(3, _ti.ti.f64, 8)
        x.from_numpy(np.zeros(8))
        v.from_numpy(v0)
        call = Kernel.quick_calls if way == "taichi" else Kernel.__call__
        returned = [call(_mixed._primal, x, v, 0.5 + step, 5 + step % 3, _ti.ti.f64, 2 + step % 2)
                    for step in range(6)]
        results[way] = returned, x.to_numpy(), v.to_numpy()
    assert results["quick"][0] == results["taichi"][0]
    np.testing.assert_array_equal(results["quick"][1], results["taichi"][1])
    np.testing.assert_array_equal(results["quick"][2], results["taichi"][2])
    launched = []
    monkeypatch.setattr(Kernel, "launch_kernel", lambda self, *a: launched.append(1) or Kernel.launch_kernel(self, *a))
    _mixed(x, v, 0.5, 5, _ti.ti.f64, 2)
    assert launched == [], "a call of an instance met before went Taichi's own way"


@pytest.mark.backend
def test_quick_calls_follow_the_arrays_to_their_instance():
    """Arrays of another element type select another compiled instance, alternately and after arrays are
    made again (their types are cached on each array, their instance per kernel)."""
    _quick_or_skip()

    @_ti.ti.kernel
    def third(a: _ti.ti.types.ndarray()):
        for i in range(a.shape[0]):
            a[i] = 1 / 3 + i

    for _ in range(3):
        for dtype, np_dtype in ((_ti.ti.f64, np.float64), (_ti.ti.f32, np.float32), (_ti.ti.i32, np.int32)):
            a = _ti.ti.ndarray(dtype, 4)
            third(a)
            third(a)
            np.testing.assert_array_equal(a.to_numpy(), (np.float64(1) / 3 + np.arange(4)).astype(np_dtype))
    b = _ti.ti.ndarray(_ti.ti.f64, (2, 2))
    with pytest.raises(Exception):      # Taichi's own error: this kernel indexes one dimension
        third(b)


@_ti.ti.kernel
def _sums(a: _ti.ti.types.ndarray(), b: _ti.ti.types.ndarray(dtype=_ti.ti.f64, ndim=2), s: _ti.ti.f64) -> _ti.ti.f64:
    total = _ti.ti.cast(0, _ti.ti.f64)
    for i, j in _ti.ti.ndrange(b.shape[0], b.shape[1]):
        b[i, j] = b[i, j] * s + a[i]
        total += b[i, j]
    return total


@pytest.mark.backend
def test_quick_calls_set_numpy_arrays_as_taichi_does(monkeypatch):
    """A C-contiguous numpy array (of an argument without a vector element) is set the quick way, as Taichi
    sets it (address, size, shape; on a GPU Taichi's launcher copies it there and back): the same arrays and
    returns either way, and no call of an instance met before goes Taichi's own way. Arrays of another
    dtype or dimension select their own instance."""
    Kernel = _quick_or_skip()
    rng = np.random.default_rng(5)
    a0, b0 = rng.standard_normal(6), rng.standard_normal((6, 4))
    results = {}
    for way in ("taichi", "quick"):
        a, b = a0.copy(), b0.copy()
        call = Kernel.quick_calls if way == "taichi" else Kernel.__call__
        returned = [call(_sums._primal, a, b, 0.5 + step) for step in range(4)]
        returned += [call(_sums._primal, a.astype(np.float32), b, 2.0), call(_sums._primal, a[:3].copy(), b[:3], 1.0)]
        results[way] = returned, a, b
    assert results["quick"][0] == results["taichi"][0]
    np.testing.assert_array_equal(results["quick"][2], results["taichi"][2])
    launched = []
    monkeypatch.setattr(Kernel, "launch_kernel", lambda self, *a: launched.append(1) or Kernel.launch_kernel(self, *a))
    b = b0.copy()
    _sums(a0, b, 0.5)
    assert launched == [], "a numpy call of an instance met before went Taichi's own way"
    np.testing.assert_array_equal(b, b0 * 0.5 + a0[:, None])


@_ti.ti.kernel
def _accumulate(a: _ti.ti.types.ndarray(), b: _ti.ti.types.ndarray(), s: _ti.ti.f64, k: _ti.ti.template()):
    for i in range(a.shape[0]):
        a[i] += s * k
        b[i] += _ti.ti.Vector([s, k, 1.0])


@pytest.mark.backend
def test_quick_calls_relaunch_a_kept_context_with_the_same_arrays():
    """On the CPU a call with the very arrays and templates of an earlier call launches the context kept
    from it, setting only its scalars, for up to REUSED_CONTEXTS sets of arrays a kernel. What it writes,
    and what Taichi's own copies read after it, are what a call that sets everything gives; so are calls on
    arrays made after others were freed (a freed array's id may come back). Set with `set_arg_ndarray`, a
    context launched twice would hand the kernel the address of the allocation record instead."""
    _quick_or_skip()
    if _ti.initialised_arch() != _ti.ti.cpu:
        pytest.skip("launch contexts are kept on the CPU only")
    for _ in range(2):
        arrays = [(_ti.ti.ndarray(_ti.ti.f64, 5), _ti.ti.Vector.ndarray(3, _ti.ti.f64, 5))
                  for _ in range(_ti.REUSED_CONTEXTS + 2)]
        expected = [(np.zeros(5), np.zeros((5, 3))) for _ in arrays]
        for a, b in arrays:
            a.fill(0)
            b.fill(0)
        for sweep in range(3):
            for j, ((a, b), (want_a, want_b)) in enumerate(zip(arrays, expected)):
                for k in (1, 2, 1):
                    s = 0.25 * (1 + sweep + j)
                    _accumulate(a, b, s, k)
                    want_a += s * k
                    want_b += [s, k, 1.0]
                np.testing.assert_array_equal(a.to_numpy(), want_a)
                np.testing.assert_array_equal(b.to_numpy(), want_b)
        kept = _accumulate._primal.__dict__["_quick_calls"][7]      # the kernel's kept contexts
        assert 0 < len(kept) <= _ti.REUSED_CONTEXTS
        del arrays


@pytest.mark.backend
def test_calls_the_quick_way_does_not_handle_go_taichis_way():
    """numpy arrays that are not C-contiguous (Taichi copies a Fortran-ordered one and back, and refuses
    one of neither order), keyword arguments, fields as templates and arguments of the wrong type work, or
    fail, as they do in Taichi."""
    _quick_or_skip()

    @_ti.ti.kernel
    def scaled(a: _ti.ti.types.ndarray(), s: _ti.ti.f64, n: _ti.ti.i32):
        for i in range(n):
            a[i] = s * i

    out = np.zeros(4)
    for _ in range(2):
        scaled(out, 2.0, 4)
    np.testing.assert_array_equal(out, [0.0, 2.0, 4.0, 6.0])
    b = np.zeros((6, 3), order="F")
    for _ in range(2):
        _sums(np.ones(6), b, 1.0)
    np.testing.assert_array_equal(b, np.full((6, 3), 2.0))
    with pytest.raises(ValueError, match="Non contiguous numpy arrays"):
        scaled(np.zeros(8)[::2], 2.0, 4)
    a = _ti.ti.ndarray(_ti.ti.f64, 4)
    for _ in range(2):
        scaled(a, s=3.0, n=4)
    np.testing.assert_array_equal(a.to_numpy(), [0.0, 3.0, 6.0, 9.0])
    with pytest.raises(Exception, match="cannot be converted|Argument"):
        scaled(a, 3.0, 2.5)
    with pytest.raises(Exception, match="missing"):
        scaled(a, 3.0)
    field = _ti.ti.field(_ti.ti.f64, 3)

    @_ti.ti.kernel
    def fill(f: _ti.ti.template(), value: _ti.ti.f64):
        for i in f:
            f[i] = value

    for value in (1.5, 2.5):
        fill(field, value)
    np.testing.assert_array_equal(field.to_numpy(), [2.5, 2.5, 2.5])


def _printed_by(script: Path) -> list:
    """The lines a script prints (Taichi's own left out), run in a fresh process with the repository
    importable; fails with its error output if it fails."""
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)})
    assert out.returncode == 0, out.stderr[-2000:]
    return [line for line in out.stdout.splitlines() if not line.startswith("[Taichi]")]


def test_quick_calls_survive_a_new_runtime(tmp_path):
    """After ti.init again (which frees every array and compiled instance) a kernel met before compiles and
    launches anew, on the new arrays."""
    script = tmp_path / "reinit.py"         # a file: Taichi reads a kernel's source
    script.write_text("import numpy as np\nfrom solver._ti import ti, quick_kernel_calls\n"
              "ti.init(arch=ti.cpu)\nassert quick_kernel_calls()\n"
              "@ti.kernel\ndef add(a: ti.types.ndarray(), s: ti.f64) -> ti.f64:\n"
              "    for i in range(a.shape[0]):\n        a[i] += s\n    return a[0]\n"
              "for k in range(2):\n"
              "    a = ti.ndarray(ti.f64, 3)\n    a.fill(1.0)\n"
              "    r = [add(a, 0.5), add(a, 0.25), add(a, 0.25)]\n"
              "    print(r, a.to_numpy().tolist())\n"
              "    ti.init(arch=ti.cpu)\n")
    assert _printed_by(script) == ["[1.5, 1.75, 2.0] [2.0, 2.0, 2.0]"] * 2


def test_quick_calls_leave_another_taichi_version_alone(tmp_path):
    """Written against Taichi 1.7.4's internals: with another version number nothing is replaced."""
    if _ti.NAME != "taichi":
        pytest.skip(f"{_ti.NAME} is not Taichi")
    script = tmp_path / "other_version.py"
    script.write_text("from solver._ti import ti, quick_kernel_calls\n"
                      "from taichi.lang.kernel_impl import Kernel\n"
                      "call = Kernel.__call__\nti.__version__ = (1, 7, 5)\n"
                      "print(quick_kernel_calls(), Kernel.__call__ is call, hasattr(Kernel, 'quick_calls'))\n")
    assert _printed_by(script) == ["False True False"]
