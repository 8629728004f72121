"""Volume files with hexahedra, wedges, pyramids and higher-order cells; orientation; unused points; units."""
import warnings

import meshio
import numpy as np
import pytest
import trimesh

import solver
from solver.errors import MeshWarning
from solver.mesh.cells import kuhn_tets

# Hexahedron corners in meshio/VTK order, as lattice offsets (dx, dy, dz).
HEX = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])


def _lattice(dims):
    """Nodes of a unit-cell lattice with dims cells, numbered lexicographically, and its cells' hexes."""
    nodes = np.stack(np.meshgrid(*[np.arange(d + 1) for d in dims], indexing="ij"), -1).reshape(-1, 3)
    cells = np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), -1).reshape(-1, 3)
    corner = cells[:, None, :] + HEX[None]
    ny1, nz1 = dims[1] + 1, dims[2] + 1
    return nodes.astype(float), (corner[..., 0] * ny1 + corner[..., 1]) * nz1 + corner[..., 2]


def _boundary_quads(dims):
    nx, ny, nz = dims
    return 2 * (nx * ny + ny * nz + nx * nz)


def _load(tmp_path, points, cells, name="mesh.vtu"):
    path = tmp_path / name
    meshio.write(path, meshio.Mesh(points, cells))
    return solver.load_mesh(path)


def test_hexahedra_with_any_numbering_split_into_conforming_tets(tmp_path):
    dims = (3, 2, 2)
    nodes, hexes = _lattice(dims)
    perm = np.random.default_rng(0).permutation(len(nodes))     # arbitrary global numbering
    points = np.empty_like(nodes)
    points[perm] = nodes
    mesh = _load(tmp_path, points, [("hexahedron", perm[hexes])])
    assert mesh.n_tets == 6 * np.prod(dims)
    assert (mesh.rest_volumes() > 0).all()
    assert mesh.rest_volumes().sum() == pytest.approx(np.prod(dims))
    # conforming: every interior quad is cut the same way from both sides, so only the box's own
    # surface (2 triangles per boundary quad) is boundary
    assert len(mesh.boundary_faces()) == 2 * _boundary_quads(dims)


def test_mixed_tets_hexahedron_wedges_pyramids_keep_all_volume_and_conform(tmp_path):
    dims = (4, 1, 1)
    nodes, hexes = _lattice(dims)
    centre = len(nodes)
    points = np.vstack([nodes, [[3.5, 0.5, 0.5]]])
    tets = kuhn_tets(np.array([[0, 0, 0]]), np.array(dims) + 1)          # cell 0: 6 tets
    wedges = np.vstack([hexes[2][[0, 1, 2, 4, 5, 6]], hexes[2][[0, 2, 3, 4, 6, 7]]])     # cell 2
    hex_faces = [[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    pyramids = np.array([np.r_[hexes[3][f], centre] for f in hex_faces])                 # cell 3
    cells = [("tetra", tets), ("hexahedron", hexes[1:2]), ("wedge", wedges), ("pyramid", pyramids)]
    mesh = _load(tmp_path, points, cells)
    assert mesh.n_tets == 6 + 6 + 2 * 3 + 6 * 2
    assert (mesh.rest_volumes() > 0).all()
    assert mesh.rest_volumes().sum() == pytest.approx(4.0)
    assert len(mesh.boundary_faces()) == 2 * _boundary_quads(dims)


@pytest.mark.parametrize("kind,corners", [("wedge", 6), ("pyramid", 5)])
def test_single_wedge_and_pyramid_keep_their_volume(tmp_path, kind, corners):
    prism = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, 3], [2, 0, 3], [0, 1, 3.0]])
    pyramid = np.array([[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0], [0.5, 0.5, 3.0]])
    points = prism if kind == "wedge" else pyramid
    volume = 2 * 1 / 2 * 3 if kind == "wedge" else 2 * 1 * 3 / 3
    # a numbering whose smallest index is not local vertex 0
    order = np.roll(np.arange(corners), 2)
    mesh = _load(tmp_path, points[order], [(kind, np.argsort(order)[None])])
    assert mesh.rest_volumes().sum() == pytest.approx(volume)
    assert (mesh.rest_volumes() > 0).all()


def _with_stand_ins(corners, nodes, first):
    """Cells (C, nodes): the corner indices (C, k), then stand-in high-order nodes first, first+1, ..."""
    high = np.repeat(first + np.arange(len(corners))[:, None], nodes - corners.shape[1], axis=1)
    return np.hstack([corners, high])


# Boundary cells as gmsh writes them beside the tets: (type, nodes, corners), same order as the tets.
@pytest.mark.parametrize("kind,nodes,boundary,suffix", [
    ("tetra10", 10, [("triangle6", 6, 3), ("line3", 3, 2)], ".vtu"),
    ("tetra35", 35, [("triangle15", 15, 3), ("line5", 5, 2), ("vertex", 1, 1)], ".msh"),   # gmsh -order 4
])
def test_higher_order_tets_keep_their_corners_with_a_note(tmp_path, kind, nodes, boundary, suffix):
    box = solver.box_mesh(cells=(2, 1, 1))
    faces = box.boundary_faces()
    extra = np.vstack([box.vertices[box.tets].mean(axis=1),        # stand-ins for the high-order nodes
                       box.vertices[faces].mean(axis=1)])
    points = np.vstack([box.vertices, extra])
    cells = [(kind, _with_stand_ins(box.tets, nodes, box.n_vertices))]
    cells += [(low, _with_stand_ins(faces[:, :corners], low_nodes, box.n_vertices + box.n_tets))
              for low, low_nodes, corners in boundary]                  # ignored by the loader
    path = tmp_path / f"p{suffix}"
    meshio.write(path, meshio.Mesh(points, cells), **({"file_format": "gmsh22"} if suffix == ".msh" else {}))
    with pytest.warns(MeshWarning, match=f"corner nodes of {box.n_tets} higher-order cells \\({kind}\\)"):
        mesh = solver.load_mesh(path)
    np.testing.assert_allclose(mesh.vertices, box.vertices)
    np.testing.assert_array_equal(mesh.tets, box.tets)


def test_messages_name_what_the_file_holds(tmp_path):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    meshio.write(tmp_path / "surface.vtk", meshio.Mesh(sphere.vertices, [("triangle", sphere.faces)]))
    with pytest.raises(solver.MeshError, match="only surface cells"):
        solver.load_mesh(tmp_path / "surface.vtk")
    curved = np.hstack([sphere.faces, sphere.faces])                    # stand-in mid-edge nodes
    meshio.write(tmp_path / "curved.vtu", meshio.Mesh(sphere.vertices, [("triangle6", curved)]))
    with pytest.raises(solver.MeshError, match=r"only surface cells \(triangle6\)"):
        solver.load_mesh(tmp_path / "curved.vtu")
    meshio.write(tmp_path / "lines.vtk", meshio.Mesh(sphere.vertices, [("line", sphere.edges[:10])]))
    with pytest.raises(solver.MeshError, match="no volume cells") as err:
        solver.load_mesh(tmp_path / "lines.vtk")
    assert "surface" not in str(err.value)


def test_surface_cells_next_to_volume_cells_are_ignored(tmp_path):
    box = solver.box_mesh(cells=(2, 2, 2))
    mesh = _load(tmp_path, box.vertices, [("triangle", box.boundary_faces()), ("tetra", box.tets)])
    np.testing.assert_array_equal(mesh.tets, box.tets)


def test_individually_reversed_tets_are_reordered():
    box = solver.box_mesh(cells=(3, 2, 2))
    tets = box.tets.copy()
    tets[[0, 7, 20, 33, 60]] = tets[[0, 7, 20, 33, 60]][:, [1, 0, 2, 3]]
    mesh = solver.TetMesh(box.vertices, tets)
    assert (mesh.rest_volumes() > 0).all()
    np.testing.assert_array_equal(np.sort(mesh.tets, axis=1), np.sort(box.tets, axis=1))
    assert len(mesh.boundary_faces()) == len(box.boundary_faces())


def test_a_genuinely_folded_mesh_is_rejected():
    box = solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(3, 3, 3))
    inner = np.flatnonzero(np.all(np.isclose(box.vertices, 1 / 3), axis=1))[0]
    folded = box.vertices.copy()
    folded[inner] = [0.8, 0.75, 0.7]                 # pushed out of its star: 6 tets turn inside out
    assert (solver.mesh.tetmesh.signed_volumes(folded, box.tets) < 0).sum() == 6
    with pytest.raises(solver.MeshError, match="folds over itself"):
        solver.TetMesh(folded, box.tets)


def test_an_unused_point_with_nan_is_ignored(tmp_path):
    box = solver.box_mesh(cells=(2, 1, 1))
    points = np.vstack([[[np.nan, 0.0, 0.0]], box.vertices])
    mesh = _load(tmp_path, points, [("tetra", box.tets + 1)])
    np.testing.assert_allclose(mesh.vertices, box.vertices)
    np.testing.assert_array_equal(mesh.original_index, np.arange(1, box.n_vertices + 1))
    used_nan = points.copy()
    used_nan[3] = np.nan
    with pytest.raises(solver.MeshError, match="used by tets have NaN"):
        solver.TetMesh(used_nan, box.tets + 1)


def test_scale_and_fit_set_the_size_in_metres(tmp_path):
    box = solver.box_mesh(size=(151.0, 20.0, 10.0), cells=(4, 1, 1))
    path = tmp_path / "big.vtu"
    solver.save_mesh(box, path)
    scaled = solver.load_mesh(path, scale=0.01)
    np.testing.assert_allclose(scaled.vertices, box.vertices * 0.01)
    fitted = solver.load_mesh(path, fit=1.5)
    np.testing.assert_allclose(np.ptp(fitted.vertices, axis=0), [1.5, 1.5 * 20 / 151, 1.5 * 10 / 151])
    surface = tmp_path / "box.obj"
    trimesh.creation.box(extents=(300.0, 100.0, 100.0)).export(surface)
    assert np.ptp(solver.load_mesh(surface, resolution=6, fit=0.3).vertices, axis=0).max() == pytest.approx(0.3)


@pytest.mark.parametrize("kwargs,match", [
    (dict(scale=0.0), "scale must be a positive number"),
    (dict(scale=-1.0), "scale must be a positive number"),
    (dict(fit=float("nan")), "fit must be a positive number"),
    (dict(fit="1"), "fit must be a positive number"),
    (dict(scale=2.0, fit=1.0), "not both"),
    (dict(repair="yes"), "repair must be True or False"),
    (dict(mesher="delaunay"), "unknown mesher"),
    (dict(edge_length=0.1), "only applies to mesher='tetwild'"),
])
def test_bad_load_arguments_raise_config_error(tmp_path, kwargs, match):
    path = tmp_path / "bar.vtu"
    solver.save_mesh(solver.box_mesh(cells=(2, 1, 1)), path)
    with pytest.raises(solver.ConfigError, match=match):
        solver.load_mesh(path, **kwargs)


def test_clean_meshes_load_without_any_warning(tmp_path):
    path = tmp_path / "bar.vtu"
    solver.save_mesh(solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(3, 3, 3)), path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solver.load_mesh(path)


@pytest.mark.parametrize("n, k", [(50, 3), (3000, 4), (60000, 4), (3_000_000, 3)])
def test_unique_rows_is_numpys_unique_of_rows_with_or_without_one_number_per_row(n, k):
    """The mesh checks' `_unique_rows` gives np.unique(rows, axis=0)'s every output, whether the rows fit in
    one int64 each (n^k < 2^63) or not (60,000^4 and 3,000,000^3 do not)."""
    from solver.mesh.tetmesh import _unique_rows

    rows = np.sort(np.random.default_rng(n).integers(0, n, size=(5000, k)), axis=1)
    rows[100:200] = rows[:100]                          # repeated rows
    expected = np.unique(rows, axis=0, return_index=True, return_inverse=True, return_counts=True)
    got = _unique_rows(rows, n, return_index=True, return_inverse=True, return_counts=True)
    for e, g in zip(expected[1:], got[1:]):
        assert np.array_equal(e.ravel(), g.ravel())
