"""solver._ti: Taichi where it is installed, else its fork Quadrants, and the runtime queries that differ."""
import importlib.util
import subprocess
import sys

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
