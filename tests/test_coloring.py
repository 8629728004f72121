"""Greedy colouring: valid, deterministic, reported, and cached per mesh."""
import numpy as np
import pytest

import solver

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA


@pytest.mark.parametrize("order", list(solver.VertexOrder))
def test_coloring_is_valid_and_deterministic(order):
    mesh = solver.box_mesh(cells=(12, 3, 3))
    a = solver.color_vertices(mesh.tets, mesh.n_vertices, order)
    b = solver.color_vertices(mesh.tets, mesh.n_vertices, order)
    assert solver.is_valid_coloring(mesh.tets, a.colors)
    np.testing.assert_array_equal(a.colors, b.colors)
    assert a.sizes.sum() == mesh.n_vertices
    assert a.n_colors == len(a.sizes)
    # A tet needs 4 colours; Kuhn-split boxes need more since neighbouring tets chain up.
    assert 4 <= a.n_colors <= 16


def test_order_is_taken_by_name_and_a_bad_one_lists_the_choices():
    mesh = solver.box_mesh(size=(1, .1, .1), cells=(4, 2, 2))
    natural = solver.color_vertices(mesh.tets, mesh.n_vertices, solver.VertexOrder.NATURAL)
    largest = solver.color_vertices(mesh.tets, mesh.n_vertices, solver.VertexOrder.LARGEST_FIRST)
    assert not np.array_equal(natural.colors, largest.colors)     # the two orders differ on this mesh
    np.testing.assert_array_equal(solver.color_vertices(mesh.tets, mesh.n_vertices, "natural").colors,
                                  natural.colors)
    np.testing.assert_array_equal(solver.color_vertices(mesh.tets, mesh.n_vertices, "largest_first").colors,
                                  largest.colors)
    keyed = solver.color_vertices(mesh.tets, mesh.n_vertices, "natural", key=mesh.topology_key())
    np.testing.assert_array_equal(keyed.colors, natural.colors)
    with pytest.raises(solver.ConfigError, match="'natural', 'largest_first'") as err:
        solver.color_vertices(mesh.tets, mesh.n_vertices, "bogus")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("tets, n_vertices, match", [
    ([[0, 1, 2, 10 ** 7]], 4, "out of range"),
    ([[0, 1, 2, -5]], 4, "out of range"),
    ([[0, 1, 2]], 4, r"not \(M, 4\)"),
    (np.zeros((0, 4), int), 4, "no tetrahedra"),
    ([[0.0, 1.0, 2.0, 3.0]], 4, "must be integers"),
    ([[0, 1, 2, 3]], 4.0, "vertex count must be an integer"),
    ([[0, 1, 2, 3]], 0, "vertex count must be an integer"),
])
def test_bad_tets_or_vertex_count_are_one_line_mesh_errors(tets, n_vertices, match):
    with pytest.raises(solver.MeshError, match=match) as err:
        solver.color_vertices(np.asarray(tets), n_vertices)
    assert "\n" not in str(err.value)


def test_invalid_colorings_are_detected():
    mesh = solver.box_mesh(cells=(3, 1, 1))
    colors = solver.color_vertices(mesh.tets, mesh.n_vertices).colors.copy()
    t = mesh.tets[0]
    colors[t[1]] = colors[t[0]]
    assert not solver.is_valid_coloring(mesh.tets, colors)
    colors[:] = -1
    assert not solver.is_valid_coloring(mesh.tets, colors)
    with pytest.raises(solver.ConfigError, match=r"one colour per vertex, at least 16 for these tets, "
                                                 r"got shape \(1,\)"):
        solver.is_valid_coloring(mesh.tets, colors[:1])


def test_coloring_is_cached_per_connectivity(monkeypatch, tmp_path):
    monkeypatch.setenv("VBD_CACHE_DIR", str(tmp_path))
    mesh = solver.box_mesh(cells=(7, 3, 2))
    key = mesh.topology_key()
    first = solver.color_vertices(mesh.tets, mesh.n_vertices, key=key)
    again = solver.color_vertices(mesh.tets, mesh.n_vertices, key=key)
    assert not first.cached and again.cached and again.seconds == 0.0
    np.testing.assert_array_equal(first.colors, again.colors)
    assert list(tmp_path.glob("colors-*.npy")), "a disk cache file is written"
    # Moving vertices does not change the key; changing connectivity does.
    moved = solver.TetMesh(mesh.vertices * 2.0, mesh.tets)
    assert moved.topology_key() == key
    assert solver.box_mesh(cells=(7, 3, 3)).topology_key() != key


def test_a_damaged_cache_file_is_coloured_again_and_replaced(monkeypatch, tmp_path):
    """A cache file cut short (a process stopped while writing an older version, a full disk) is not an
    error: the mesh is coloured again and the file rewritten whole; no .part file is left behind."""
    from solver.mesh import coloring

    monkeypatch.setenv("VBD_CACHE_DIR", str(tmp_path))
    mesh = solver.box_mesh(cells=(4, 3, 2))
    key = mesh.topology_key()
    first = solver.color_vertices(mesh.tets, mesh.n_vertices, key=key)
    (written,) = tmp_path.glob("colors-*.npy")
    for damaged in (written.read_bytes()[:100], b"", b"not a numpy file"):
        written.write_bytes(damaged)
        monkeypatch.setattr(coloring, "_memory_cache", {})
        again = solver.color_vertices(mesh.tets, mesh.n_vertices, key=key)
        assert not again.cached
        np.testing.assert_array_equal(again.colors, first.colors)
        np.testing.assert_array_equal(np.load(written), first.colors)
    assert sorted(p.name for p in tmp_path.iterdir()) == [written.name]


def test_a_cache_that_cannot_be_written_leaves_nothing_behind(monkeypatch, tmp_path):
    """Writing the cache fails part way (a full disk): the colouring is still returned, and neither a cache
    file nor a half-written .part file is left in the folder."""
    from solver.mesh import coloring

    def full_disk(file, colors):
        file.write(b"\x93NUMPY")
        raise OSError(28, "No space left on device")

    monkeypatch.setenv("VBD_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(coloring, "_memory_cache", {})
    monkeypatch.setattr(coloring.np, "save", full_disk)
    mesh = solver.box_mesh(cells=(3, 3, 2))
    result = solver.color_vertices(mesh.tets, mesh.n_vertices, key=mesh.topology_key())
    assert solver.is_valid_coloring(mesh.tets, result.colors) and not result.cached
    assert list(tmp_path.iterdir()) == []


def test_simulation_leaves_fixed_vertices_out_of_the_color_sets():
    mesh = solver.box_mesh(cells=(6, 2, 2))
    fixed = mesh.vertices[:, 0] < 1e-9
    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), fixed=fixed, iterations=1)
    assert (sim.colors[fixed] == -1).all()
    assert (sim.colors[~fixed] >= 0).all()
    assert sim.topology.n_slots == (~fixed).sum()
    assert sim.n_colors == len(np.unique(sim.colors[~fixed]))


def test_more_than_64_colors_is_reported():
    """68 vertices that all share tets pairwise (tets (i, j, 66, 67)) need 68 colours."""
    i, j = np.triu_indices(66, k=1)
    tets = np.stack([i, j, np.full_like(i, 66), np.full_like(i, 67)], axis=1)
    with pytest.raises(solver.MeshError, match="more than 64 colours"):
        solver.color_vertices(tets, 68)


def test_a_cache_written_by_other_coloring_code_is_never_read(monkeypatch, tmp_path):
    """The disk cache is keyed on the source of `_greedy`: a homework starter never shows a colouring
    that the reference solution (or an earlier version of the student's code) cached."""
    from solver.mesh import coloring

    monkeypatch.setenv("VBD_CACHE_DIR", str(tmp_path))
    mesh = solver.box_mesh(cells=(5, 2, 3))
    key = mesh.topology_key()
    real = coloring._greedy_digest()
    assert len(real) == 12
    monkeypatch.setitem(coloring._code_digest, "greedy", "other0code00")
    other = solver.color_vertices(mesh.tets, mesh.n_vertices, key=key)       # "other code" fills the cache
    (written,) = tmp_path.glob("colors-*.npy")
    assert "other0code00" in written.name and real not in written.name
    swapped = np.where(other.colors == 0, 1, np.where(other.colors == 1, 0, other.colors)).astype(np.int32)
    np.save(written, swapped)                      # a different valid colouring under the other code's key
    monkeypatch.setattr(coloring, "_memory_cache", {})
    assert solver.color_vertices(mesh.tets, mesh.n_vertices, key=key).cached   # same code: read back
    monkeypatch.setitem(coloring._code_digest, "greedy", real)
    monkeypatch.setattr(coloring, "_memory_cache", {})
    mine = solver.color_vertices(mesh.tets, mesh.n_vertices, key=key)
    assert not mine.cached
    np.testing.assert_array_equal(mine.colors, other.colors)
    assert not np.array_equal(mine.colors, swapped)
