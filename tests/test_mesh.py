"""Meshes: generators, every supported file format, boundary extraction, and every kind of bad input."""
import os

import meshio
import numpy as np
import pytest
import trimesh

import solver
from solver.mesh.cells import signed_volumes


def test_box_mesh_is_conforming_positive_and_fills_the_box():
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.2), cells=(10, 2, 3))
    assert mesh.n_tets == 6 * 10 * 2 * 3
    assert mesh.n_vertices == 11 * 3 * 4
    vol = mesh.rest_volumes()
    assert (vol > 0).all()
    assert vol.sum() == pytest.approx(1.0 * 0.1 * 0.2)
    # Conforming: every interior face is shared by exactly two tets, so the boundary is exactly the
    # box surface: 2 triangles per boundary quad.
    faces = mesh.boundary_faces()
    assert len(faces) == 2 * 2 * (10 * 2 + 10 * 3 + 2 * 3)


@pytest.mark.parametrize("cells", [2, 4, 6])
def test_ball_mesh_is_conforming_round_and_free_of_slivers(cells):
    """Its boundary is the sphere (every boundary node at the radius, no interior face left open: a
    conforming split), its volume approaches the ball's, and no tet is a sliver or badly shaped."""
    center = np.array([0.3, -0.2, 1.0])
    mesh = solver.ball_mesh(radius=0.1, cells=cells, center=center)
    assert mesh.n_vertices == (cells + 1) ** 3 and mesh.n_tets == 6 * cells ** 3
    faces = mesh.boundary_faces()
    assert len(faces) == 6 * 2 * cells ** 2                       # a quad sphere: 2 triangles per cube face cell
    radii = np.linalg.norm(mesh.vertices[np.unique(faces)] - center, axis=1)
    np.testing.assert_allclose(radii, 0.1, rtol=1e-12)
    inner = np.setdiff1d(np.arange(mesh.n_vertices), faces)
    assert (np.linalg.norm(mesh.vertices[inner] - center, axis=1) < 0.1 - 1e-3).all()
    x = mesh.vertices
    normals = np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    assert ((normals * (x[faces].mean(axis=1) - center)).sum(axis=1) > 0).all()
    quality = mesh.quality()
    assert quality.n_slivers == 0 and quality.n_inverted == 0
    assert quality.min_radius_ratio > 0.65 and 30 < quality.min_dihedral_degrees < quality.max_dihedral_degrees < 111
    ball = 4 / 3 * np.pi * 0.1 ** 3
    assert {2: 0.77, 4: 0.93, 6: 0.97}[cells] * ball < mesh.rest_volumes().sum() < ball


def test_ball_mesh_is_symmetric_under_every_axis_reflection():
    mesh = solver.ball_mesh(radius=1.0, cells=4)
    for axis in range(3):
        mirrored = mesh.vertices.copy()
        mirrored[:, axis] *= -1
        order = np.lexsort(mesh.vertices.T)
        np.testing.assert_allclose(mirrored[np.lexsort(mirrored.T)], mesh.vertices[order], atol=1e-15)


@pytest.mark.parametrize("kwargs, match", [
    (dict(radius=0.0), "ball radius must be a positive length in m, got 0.0"),
    (dict(radius=float("nan")), "ball radius must be a positive length"),
    (dict(radius="1"), "ball radius must be a positive length in m, got '1'"),
    (dict(cells=3), r"ball cells must be an even integer >= 2 \(cells per diameter\), got 3"),
    (dict(cells=4.0), "ball cells must be an even integer"),
    (dict(cells=0), "ball cells must be an even integer"),
    (dict(center=(0.0, float("inf"), 0.0)), "ball center must be three finite coordinates in m"),
    (dict(center=("a", 0.0, 0.0)), r"ball center must be three finite coordinates in m, got \('a', 0.0, 0.0\)"),
    (dict(center=(0.0, 0.0)), r"got \(0.0, 0.0\)"),
])
def test_ball_mesh_refuses_nonsense_in_one_line(kwargs, match):
    with pytest.raises(solver.MeshError, match=match):
        solver.ball_mesh(**kwargs)


@pytest.mark.parametrize("kwargs, match", [
    (dict(size=(0.1, 0.0, 0.1)), r"box size must be three positive lengths, got \[0.1, 0.0, 0.1\]"),
    (dict(cells=(2, 0, 1)), r"box cells must be three integers >= 1, got \[2, 0, 1\]"),
    (dict(origin="abc"), "box origin must be three finite coordinates in m, got 'abc'"),
    (dict(origin=(0.0, 0.0)), r"box origin must be three finite coordinates in m, got \(0.0, 0.0\)"),
    (dict(origin=(0.0, float("nan"), 0.0)), "box origin must be three finite coordinates in m"),
])
def test_box_mesh_refuses_nonsense_in_one_line(kwargs, match):
    with pytest.raises(solver.MeshError, match=match):
        solver.box_mesh(**{"size": (0.1, 0.1, 0.1), "cells": (1, 1, 1), **kwargs})


def test_boundary_faces_point_outward():
    mesh = solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(3, 3, 3))
    x = mesh.vertices
    f = mesh.boundary_faces()
    normals = np.cross(x[f[:, 1]] - x[f[:, 0]], x[f[:, 2]] - x[f[:, 0]])
    centroid = x[f].mean(axis=1)
    assert ((normals * (centroid - 0.5)).sum(axis=1) > 0).all()
    # Divergence theorem: sum over faces of (centroid . area normal) / 3 = volume.
    assert (centroid * normals / 2).sum() / 3 == pytest.approx(1.0)


def test_boundary_faces_takes_a_mesh_or_its_tets():
    mesh = solver.box_mesh(cells=(2, 2, 1))
    np.testing.assert_array_equal(solver.boundary_faces(mesh), mesh.boundary_faces())
    np.testing.assert_array_equal(solver.boundary_faces(mesh.tets.tolist()), mesh.boundary_faces())
    for bad in (mesh.vertices, mesh.tets[:, :3], 7):
        with pytest.raises(solver.MeshError, match=r"needs a TetMesh or an \(M, 4\) integer array"):
            solver.boundary_faces(bad)


@pytest.mark.parametrize("suffix", [".msh", ".vtu", ".vtk", ".mesh"])
def test_volume_formats_round_trip(tmp_path, suffix):
    mesh = solver.box_mesh(cells=(4, 2, 2))
    path = tmp_path / f"bar{suffix}"
    solver.save_mesh(mesh, path)
    loaded = solver.load_mesh(path)
    np.testing.assert_allclose(loaded.vertices, mesh.vertices)
    np.testing.assert_array_equal(loaded.tets, mesh.tets)


def test_tetgen_node_ele_files(tmp_path):
    mesh = solver.box_mesh(cells=(3, 1, 1))
    meshio.write(tmp_path / "bar.node", meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)]), file_format="tetgen")
    loaded = solver.load_mesh(tmp_path / "bar.node")
    assert loaded.n_tets == mesh.n_tets
    assert loaded.rest_volumes().sum() == pytest.approx(mesh.rest_volumes().sum())


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".ply", ".off"])
def test_closed_surfaces_are_tetrahedralised(tmp_path, suffix):
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    path = tmp_path / f"sphere{suffix}"
    sphere.export(path)
    mesh = solver.load_mesh(path, resolution=10)
    assert (mesh.rest_volumes() > 0).all()
    # Voxel volume converges to the sphere's volume; at 10 voxels across it is within 15 %.
    assert mesh.rest_volumes().sum() == pytest.approx(sphere.volume, rel=0.15)
    finer = solver.load_mesh(path, resolution=20)
    assert abs(finer.rest_volumes().sum() - sphere.volume) < abs(mesh.rest_volumes().sum() - sphere.volume)


def test_save_surface_formats_write_the_boundary(tmp_path):
    mesh = solver.box_mesh(cells=(2, 2, 2))
    solver.save_mesh(mesh, tmp_path / "box.obj")
    surface = trimesh.load(tmp_path / "box.obj", force="mesh")
    assert surface.is_watertight
    assert surface.volume == pytest.approx(mesh.rest_volumes().sum())


def test_all_negative_orientation_is_flipped_and_unreferenced_vertices_dropped():
    mesh = solver.box_mesh(cells=(2, 1, 1))
    flipped = mesh.tets[:, [0, 2, 1, 3]]
    extra = np.vstack([mesh.vertices, [[9.0, 9.0, 9.0]]])
    moved = np.vstack([[[5.0, 5.0, 5.0]], extra])            # unreferenced vertex first
    fixed = solver.TetMesh(moved, flipped + 1)
    assert (fixed.rest_volumes() > 0).all()
    assert fixed.n_vertices == mesh.n_vertices
    np.testing.assert_array_equal(fixed.original_index, np.arange(1, mesh.n_vertices + 1))


def _bad(vertices, tets, match):
    with pytest.raises(solver.MeshError, match=match):
        solver.TetMesh(vertices, tets)


def test_bad_meshes_raise_mesh_error():
    mesh = solver.box_mesh(cells=(2, 1, 1))
    X, T = mesh.vertices, mesh.tets
    _bad(X, np.zeros((0, 4), int), "no tetrahedra")
    _bad(X, T + 100, "out of range")
    _bad(X, np.vstack([T, [[-1, 0, 1, 2]]]), "out of range")
    _bad(X, [[0, 1, 2, 3], [0, 1]], "rows of 4 vertex indices")
    nan = X.copy()
    nan[3, 1] = np.nan
    _bad(nan, T, "NaN")
    inf = X.copy()
    inf[0, 0] = np.inf
    _bad(inf, T, "NaN or infinite")
    flat = X.copy()
    flat[:, 2] = 0.0
    _bad(flat, T, "zero volume")
    _bad(X, np.vstack([T, T[:1, [1, 0, 2, 3]]]), "duplicate")
    _bad(X, np.vstack([T, [[0, 0, 1, 2]]]), "twice")
    _bad(X[:, :2], T, r"\(N, 3\)")
    _bad(X, T.astype(float), "integers")


def test_bad_files_raise_mesh_error_with_the_path(tmp_path):
    with pytest.raises(solver.MeshError, match="not found"):
        solver.load_mesh(tmp_path / "missing.msh")
    garbage = tmp_path / "garbage.msh"
    garbage.write_bytes(b"\x00\x01 this is not a mesh")
    with pytest.raises(solver.MeshError, match="cannot read"):
        solver.load_mesh(garbage)
    surface_only = tmp_path / "surface.vtk"
    sphere = trimesh.creation.icosphere(subdivisions=1)
    meshio.write(surface_only, meshio.Mesh(sphere.vertices, [("triangle", sphere.faces)]))
    with pytest.raises(solver.MeshError, match="only surface cells"):
        solver.load_mesh(surface_only)
    open_surface = tmp_path / "open.obj"
    trimesh.Trimesh(sphere.vertices, sphere.faces[:-3]).export(open_surface)
    with pytest.raises(solver.MeshError, match="not closed"):
        solver.load_mesh(open_surface)
    with pytest.raises(solver.MeshError, match="folder"):
        solver.load_mesh(tmp_path)
    with pytest.raises(solver.MeshError, match="resolution"):
        solver.load_mesh(_closed(tmp_path), resolution=0)


def test_a_cell_naming_a_missing_point_is_a_mesh_error(tmp_path):
    damaged = tmp_path / "damaged.vtk"             # legacy VTK: one tet, but only 4 points (0..3)
    damaged.write_text("# vtk DataFile Version 2.0\ndamaged\nASCII\nDATASET UNSTRUCTURED_GRID\n"
                       "POINTS 4 double\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n"
                       "CELLS 1 5\n4 0 1 2 7\nCELL_TYPES 1\n10\n")
    with pytest.raises(solver.MeshError, match=r"damaged.vtk: tetra cell 0 names point 7, but the file "
                                               r"has 4 points \(0 to 3\)"):
        solver.load_mesh(damaged)


@pytest.mark.parametrize("call", [lambda mesh: solver.load_mesh(123), lambda mesh: solver.save_mesh(mesh, 123)],
                         ids=["load_mesh", "save_mesh"])
def test_a_path_that_is_not_a_path_is_a_config_error(tmp_path, call):
    with pytest.raises(solver.ConfigError, match="path must be a str, bytes or pathlib.Path, got int 123"):
        call(solver.box_mesh(cells=(1, 1, 1)))


BOX = solver.box_mesh(cells=(1, 1, 1))


@pytest.mark.parametrize("mesh, point_data, match", [
    ("m", None, "needs a TetMesh or a \\(vertices, tets\\) pair, got str"),
    ((np.zeros((4, 2)), BOX.tets), None, r"vertices must be an \(N, 3\) array of finite numbers, got shape \(4, 2\)"),
    ((BOX.vertices, BOX.tets + 100), None, r"tets must be an \(M, 4\) array of indices below 8"),
    ((BOX.vertices, BOX.tets.astype(float)), None, r"tets must be an \(M, 4\) array of indices"),
    (BOX, {"a": np.zeros(3)}, r"point_data\['a'\] has shape \(3,\); it needs one row per vertex, \(8,\)"),
    (BOX, "x", "point_data must be a dict of per-vertex arrays, got str"),
])
def test_save_mesh_refuses_what_it_cannot_write_in_one_line(tmp_path, mesh, point_data, match):
    path = tmp_path / "out.vtu"
    with pytest.raises(solver.MeshError, match=match):
        solver.save_mesh(mesh, path, point_data=point_data)
    assert not path.exists()


@pytest.mark.parametrize("build, match", [
    (lambda: solver.box_mesh(size="big", cells=(1, 1, 1)), "box size must be three positive lengths in m, got 'big'"),
    (lambda: solver.box_mesh(cells=(100000,) * 3), "more than 10,000,000; use fewer cells"),
    (lambda: solver.TetMesh([[0, 0, 0], [1, 0]], BOX.tets[:1]), "its rows differ in length"),
    (lambda: solver.TetMesh(BOX.vertices + 1j, BOX.tets), "vertices must be real numbers"),
    (lambda: solver.sliver_box_mesh(jitter="x"), r"sliver jitter must be a number of cells in \[0, 0.5\)"),
    (lambda: solver.sliver_box_mesh(jitter=1e6), r"sliver jitter must be a number of cells in \[0, 0.5\)"),
    (lambda: solver.sliver_box_mesh(seed=-1), "sliver seed must be a whole number >= 0, got -1"),
    (lambda: solver.sliver_box_mesh(cells=(0, 1, 1)), r"box cells must be three integers >= 1, got \[0, 1, 1\]"),
    (lambda: solver.TetMesh(BOX.vertices, BOX.tets, original_index=np.array([7])),
     r"original_index must hold one index per vertex, \(8,\), got shape \(1,\)"),
])
def test_mesh_builders_refuse_bad_arguments_in_one_line(build, match):
    with pytest.raises(solver.MeshError, match=match):
        build()


@pytest.mark.parametrize("name", ["box.xdmf", "box.h5m"])
def test_a_format_that_needs_h5py_says_so(tmp_path, name):
    try:
        import h5py  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("h5py is installed: these formats are written")
    with pytest.raises(solver.MeshError, match="needs the Python package h5py; pip install h5py"):
        solver.save_mesh(BOX, tmp_path / name)


def test_a_bytes_path_is_a_path(tmp_path):
    mesh = solver.box_mesh(cells=(2, 1, 1))
    path = os.fsencode(tmp_path / "bar.vtk")
    solver.save_mesh(mesh, path)
    np.testing.assert_array_equal(solver.load_mesh(path).tets, mesh.tets)


def test_a_closed_surface_with_a_nan_vertex_names_the_nan(tmp_path):
    lines = trimesh.exchange.obj.export_obj(trimesh.creation.box()).splitlines()
    third = [k for k, line in enumerate(lines) if line.startswith("v ")][2]
    lines[third] = "v nan 0.5 0.5"
    path = tmp_path / "nan.obj"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(solver.MeshError, match=r"nan.obj: 1 vertices used by triangles have NaN or infinite "
                                               r"coordinates \(first: vertex 2 counting from 0, at "
                                               r"\[nan, 0.5, 0.5\]\)"):
        solver.load_mesh(path)


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
@pytest.mark.parametrize("damage", ["cut in POINTS", "POINTS count too large"])
@pytest.mark.filterwarnings("ignore:string or file could not be read:DeprecationWarning")   # numpy in meshio's reader
def test_a_truncated_vtk_file_is_called_damaged(tmp_path, binary, damage):
    mesh = solver.box_mesh(cells=(2, 1, 1))
    path = tmp_path / "bar.vtk"
    meshio.write(path, meshio.Mesh(mesh.vertices, [("tetra", mesh.tets)]), binary=binary)
    data = path.read_bytes()
    if damage == "cut in POINTS":
        data = data[:data.index(b"POINTS") + 60]
    else:
        data = data.replace(b"POINTS %d" % mesh.n_vertices, b"POINTS %d" % (mesh.n_vertices + 50))
    path.write_bytes(data)
    with pytest.raises(solver.MeshError, match=r"bar.vtk: cannot read this file, it is damaged, truncated .*"
                                               r"\(meshio: .+\); export it again") as err:
        solver.load_mesh(path)
    assert "\n" not in str(err.value)


def _closed(tmp_path):
    path = tmp_path / "closed.obj"
    trimesh.creation.box().export(path)
    return path


def test_signed_volume_helper():
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    assert signed_volumes(X, np.array([[0, 1, 2, 3]]))[0] == pytest.approx(1 / 6)
    assert signed_volumes(X, np.array([[0, 2, 1, 3]]))[0] == pytest.approx(-1 / 6)


@pytest.mark.parametrize("name, match", [
    ("missing-folder/box.vtu", "cannot write .*check that the folder exists"),
    ("box.xyz", "cannot write this format .*use a suffix meshio writes"),
])
def test_save_mesh_errors_are_mesh_errors(tmp_path, name, match):
    mesh = solver.box_mesh(size=(1.0, 1.0, 1.0), cells=(1, 1, 1))
    with pytest.raises(solver.MeshError, match=match):
        solver.save_mesh(mesh, tmp_path / name)
    assert list(tmp_path.iterdir()) == []
