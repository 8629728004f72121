"""Task coloring: greedy graph colouring of the vertices (lecture notes, chapter 4)."""
import numpy as np
import pytest

from gradelib import bar, require
from solver.mesh.coloring import VertexOrder, color_vertices, is_valid_coloring
from solver.mesh.topology import vertex_neighbours

pytestmark = pytest.mark.task("coloring")


def color(tets, n, order=VertexOrder.NATURAL):
    require("coloring")
    return color_vertices(tets, n, order)       # no cache key: your _greedy always runs


def shuffled(mesh, seed):
    """The same mesh with its vertices renumbered at random."""
    perm = np.random.default_rng(seed).permutation(mesh.n_vertices)
    inverse = np.argsort(perm)
    return inverse[mesh.tets].astype(np.int32), mesh.n_vertices


@pytest.mark.parametrize("cells", [(1, 1, 1), (6, 2, 2), (20, 3, 3)])
def test_coloring_is_valid(cells):
    mesh = bar(cells=cells)
    result = color(mesh.tets, mesh.n_vertices)
    assert result.colors.shape == (mesh.n_vertices,)
    assert is_valid_coloring(mesh.tets, result.colors), "two vertices of one tet share a colour"
    assert result.n_colors == result.colors.max() + 1
    assert (np.bincount(result.colors) > 0).all(), "colours must be 0..n_colors-1 without gaps"


@pytest.mark.parametrize("order", [VertexOrder.NATURAL, VertexOrder.LARGEST_FIRST])
def test_every_vertex_gets_the_first_free_color(order):
    tets, n = shuffled(bar(cells=(10, 3, 2)), seed=5)
    result = color(tets, n, order)
    offsets, neighbours = vertex_neighbours(tets, n)
    degree = np.diff(offsets)
    visit = np.arange(n) if order is VertexOrder.NATURAL else np.argsort(-degree, kind="stable")
    rank = np.empty(n, dtype=int)
    rank[visit] = np.arange(n)
    for v in range(n):
        earlier = [u for u in neighbours[offsets[v]:offsets[v + 1]] if rank[u] < rank[v]]
        taken = set(result.colors[earlier].tolist())
        first_free = next(c for c in range(len(taken) + 1) if c not in taken)
        assert result.colors[v] == first_free, (f"vertex {v} got colour {result.colors[v]}, but the first "
                                                f"colour free among its earlier neighbours is {first_free}")


def test_greedy_returns_the_number_of_colors():
    """`_greedy` itself returns n_colors: `color_vertices` reads it to refuse a mesh needing too many colours."""
    require("coloring")
    from solver.mesh.coloring import _greedy

    tets, n = shuffled(bar(cells=(6, 2, 2)), seed=3)
    offsets, neighbours = vertex_neighbours(tets, n)
    colors = np.full(n, -1, dtype=np.int32)
    n_colors = _greedy(offsets.astype(np.int32), neighbours.astype(np.int32), np.arange(n, dtype=np.int32), colors)
    assert n_colors == colors.max() + 1, f"_greedy returned n_colors = {n_colors}, but it used {colors.max() + 1} colours"


def test_a_larger_shuffled_mesh():
    tets, n = shuffled(bar(cells=(16, 4, 4)), seed=1)
    result = color(tets, n)
    assert is_valid_coloring(tets, result.colors)
    offsets, _ = vertex_neighbours(tets, n)
    assert result.n_colors <= np.diff(offsets).max() + 1     # greedy never needs more than degree + 1
