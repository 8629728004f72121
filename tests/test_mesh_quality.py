"""Tet quality measures against independent formulas, sliver warnings and repair, inversion counts."""
import numpy as np
import pytest

import solver
from solver.mesh.tetmesh import face_components
from solver.mesh.quality import degenerate_mask, dihedral_angles, radius_ratio

REGULAR = np.array([[1.0, 1, 1], [1, -1, -1], [-1, -1, 1], [-1, 1, -1]])


def _random_tets(n=20, seed=1):
    x = np.random.default_rng(seed).normal(size=(4 * n, 3))
    return x, np.arange(4 * n).reshape(n, 4)


def test_regular_and_cube_tets_have_their_known_shape():
    assert radius_ratio(REGULAR, np.array([[0, 1, 2, 3]]))[0] == pytest.approx(1.0)
    np.testing.assert_allclose(np.degrees(dihedral_angles(REGULAR, np.array([[0, 1, 2, 3]]))),
                               np.degrees(np.arccos(1 / 3)))
    # Kuhn tets of a cube: dihedral angles 45, 60 and 90 degrees
    q = solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(2, 2, 2)).quality()
    assert (q.min_dihedral_degrees, q.max_dihedral_degrees) == (pytest.approx(45.0), pytest.approx(90.0))
    assert q.n_slivers == q.n_inverted == q.n_degenerate == 0


def test_dihedral_angles_match_the_angle_between_projected_opposite_vertices():
    x, tets = _random_tets()
    angles = dihedral_angles(x, tets)
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    for t, tet in enumerate(tets):
        for e, (i, j) in enumerate(edges):
            k, l = [v for v in range(4) if v not in (i, j)]
            axis = x[tet[j]] - x[tet[i]]
            axis /= np.linalg.norm(axis)
            u, w = x[tet[k]] - x[tet[i]], x[tet[l]] - x[tet[i]]
            u, w = u - (u @ axis) * axis, w - (w @ axis) * axis
            expected = np.arccos(u @ w / np.linalg.norm(u) / np.linalg.norm(w))
            assert angles[t, e] == pytest.approx(expected, abs=1e-9)


def test_radius_ratio_matches_circumsphere_and_insphere_from_scratch():
    x, tets = _random_tets()
    ratio = radius_ratio(x, tets)
    for t, tet in enumerate(tets):
        p = x[tet]
        centre = np.linalg.solve(2 * (p[1:] - p[0]), (p[1:] ** 2).sum(1) - (p[0] ** 2).sum())
        r_circ = np.linalg.norm(centre - p[0])
        volume = np.linalg.det(p[1:] - p[0]) / 6
        area = sum(np.linalg.norm(np.cross(p[b] - p[a], p[c] - p[a])) / 2
                   for a, b, c in [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)])
        r_in = 3 * abs(volume) / area
        assert ratio[t] == pytest.approx(np.sign(volume) * 3 * r_in / r_circ, rel=1e-9)


def test_flat_and_inverted_tets_are_counted():
    flat = REGULAR.copy()
    flat[3] = (flat[0] + flat[1] + flat[2]) / 3 + [0, 0, 1e-12]
    x = np.vstack([REGULAR, flat])
    tets = np.array([[0, 1, 2, 3], [0, 2, 1, 3], [4, 5, 6, 7]])
    assert degenerate_mask(x, tets).tolist() == [False, False, True]
    q = solver.mesh.quality.mesh_quality(x, tets)
    assert (q.n_inverted, q.n_degenerate, q.n_slivers) == (1, 1, 2)


def test_det_F_and_inverted_count():
    mesh = solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(2, 2, 2))
    rest = mesh.vertices
    np.testing.assert_allclose(solver.det_F(rest, mesh.tets, 2.0 * rest), 8.0)
    assert solver.inverted_count(rest, mesh.tets, rest) == 0
    mirrored = rest * [-1.0, 1.0, 1.0]
    assert solver.inverted_count(rest, mesh.tets, mirrored) == mesh.n_tets
    pushed = rest.copy()
    corner = np.flatnonzero((rest == 0).all(axis=1))[0]
    pushed[corner] = [0.9, 0.9, 0.9]                     # through every tet at that corner
    touching = (mesh.tets == corner).any(axis=1)
    assert solver.inverted_count(rest, mesh.tets, pushed) == np.count_nonzero(
        solver.det_F(rest, mesh.tets[touching], pushed) <= 0) > 0


def test_sliver_mesh_warns_on_load_and_repair_drops_the_slivers(tmp_path):
    mesh = solver.sliver_box_mesh()
    q = mesh.quality()
    assert q.n_slivers > 20 and q.min_dihedral_degrees < 1.0
    path = tmp_path / "slivers.vtu"
    solver.save_mesh(mesh, path)
    with pytest.warns(solver.MeshQualityWarning, match=f"{q.n_slivers} of {mesh.n_tets} tets are slivers.*repair=True"):
        solver.load_mesh(path)
    with pytest.warns(solver.MeshQualityWarning, match="hold the mesh together, so repair kept them"):
        repaired = solver.load_mesh(path, repair=True)
    left = repaired.quality().n_slivers
    assert 0 < left < q.n_slivers / 2
    assert repaired.n_tets == mesh.n_tets - (q.n_slivers - left)
    assert (face_components(repaired.tets) == 0).all()
    # slivers are nearly flat: the volume hardly changes
    assert repaired.rest_volumes().sum() == pytest.approx(mesh.rest_volumes().sum(), rel=0.02)
    np.testing.assert_allclose(repaired.vertices, mesh.vertices[repaired.original_index])


def test_repair_drops_zero_volume_tets_that_otherwise_fail(tmp_path):
    box = solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(2, 2, 2))
    bottom = np.flatnonzero(box.vertices[:, 2] == 0)[:4]          # four corners in the plane z = 0
    path = tmp_path / "flat.vtu"
    solver.save_mesh((box.vertices, np.vstack([box.tets, bottom])), path)
    with pytest.raises(solver.MeshError, match="zero volume.*repair=True"):
        solver.load_mesh(path)
    repaired = solver.load_mesh(path, repair=True)
    np.testing.assert_array_equal(repaired.tets, box.tets)


def test_repair_drops_all_boundary_slivers_of_a_good_mesh():
    box = solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(2, 2, 2))
    # a flat cap on the top face: 4 new points just above it, Delaunay-like sliver glued to one face
    face = box.boundary_faces()[box.vertices[box.boundary_faces()].mean(axis=1)[:, 2] > 0.999][0]
    lid = box.vertices[face].mean(axis=0) + [0.0, 0.0, 1e-3]
    x = np.vstack([box.vertices, lid])
    tets = np.vstack([box.tets, np.r_[face, box.n_vertices]])
    mesh = solver.TetMesh(x, tets)
    assert mesh.quality().n_slivers == 1
    repaired = mesh.without_slivers()
    np.testing.assert_array_equal(repaired.tets, box.tets)
    assert repaired.n_vertices == box.n_vertices


def test_face_components_split_at_edges_and_vertices():
    mesh = solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(2, 2, 2))
    assert (face_components(mesh.tets) == 0).all()
    # two tets sharing only an edge, and one sharing only a vertex with them
    tets = np.array([[0, 1, 2, 3], [0, 1, 4, 5], [5, 6, 7, 8]])
    labels = face_components(tets)
    assert len(set(labels.tolist())) == 3
