"""Surfaces to tets: fTetWild (optional extra, cached) and the voxel fallback's face-connected pieces."""
import os
import sys

import numpy as np
import pytest
import trimesh

import solver
from solver.mesh.tetmesh import face_components
from solver.mesh.tetrahedralize import tetwild_available
from solver.errors import MeshWarning
from solver.mesh.voxelize import largest_face_connected, tetrahedralize_surface

needs_tetwild = pytest.mark.skipif(
    not tetwild_available(), reason="optional mesher pytetwild not installed (pip install -r requirements-mesh.txt)")


def _boxes(*boxes):
    """Vertices and faces of several closed boxes (min corner, max corner), not merged."""
    parts = [trimesh.creation.box(bounds=np.array(b, dtype=float)) for b in boxes]
    vertices = np.vstack([p.vertices for p in parts])
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    faces = np.vstack([p.faces + o for p, o in zip(parts, offsets)])
    return vertices, faces


def test_voxels_attached_by_an_edge_are_dropped():
    # a 4x4x4 block and a 1x1x2 column touching it along one vertical edge
    vertices, faces = _boxes([[0, 0, 0], [4, 4, 4]], [[4, 4, 0], [5, 5, 2]])
    with pytest.warns(MeshWarning, match="dropped 2 of 66 voxels"):
        points, tets = tetrahedralize_surface(vertices, faces, resolution=5)
    mesh = solver.TetMesh(points, tets)
    assert mesh.rest_volumes().sum() == pytest.approx(64.0)
    assert (face_components(mesh.tets) == 0).all()


def test_voxels_attached_by_a_corner_and_islands_are_dropped():
    vertices, faces = _boxes([[0, 0, 0], [4, 4, 4]], [[4, 4, 4], [5, 5, 5]], [[6, 0, 0], [7, 1, 1]])
    with pytest.warns(MeshWarning, match="dropped 2 of 66 voxels"):
        points, tets = tetrahedralize_surface(vertices, faces, resolution=7)
    mesh = solver.TetMesh(points, tets)
    assert mesh.rest_volumes().sum() == pytest.approx(64.0)


def test_largest_face_connected_grid_rule():
    grid = np.zeros((4, 4, 4), bool)
    grid[:2, :2, :2] = True
    grid[2, 2, 0] = grid[2, 2, 1] = True        # two voxels on an edge of the block
    kept = largest_face_connected(grid)
    assert kept.sum() == 8 and not kept[2, 2].any()
    grid[2, 1, 0] = True                        # now joined through a face
    assert largest_face_connected(grid).sum() == 11


def test_missing_tetwild_gives_a_config_error_naming_the_fix(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pytetwild", None)       # import fails as if not installed
    path = tmp_path / "box.obj"
    trimesh.creation.box().export(path)
    with pytest.raises(solver.ConfigError, match="pip install -r requirements-mesh.txt"):
        solver.load_mesh(path, mesher="tetwild")


@needs_tetwild
def test_tetwild_fills_a_sphere_with_well_shaped_tets_and_caches_them(tmp_path, monkeypatch):
    monkeypatch.setenv("VBD_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    path = tmp_path / "sphere.obj"
    sphere.export(path)
    mesh = solver.load_mesh(path, mesher=solver.Mesher.TETWILD, edge_length=0.04, fit=0.2)
    assert np.ptp(mesh.vertices, axis=0).max() == pytest.approx(0.2, rel=0.02)
    assert mesh.rest_volumes().sum() == pytest.approx(sphere.volume * 0.1 ** 3, rel=0.03)
    quality = mesh.quality()
    assert quality.n_slivers == 0 and quality.min_dihedral_degrees > 5
    assert len(os.listdir(tmp_path / "cache")) == 1
    assert sorted(os.listdir(tmp_path)) == ["cache", "sphere.obj"]      # no scratch files left here
    again = solver.load_mesh(path, mesher="tetwild", edge_length=0.04, fit=0.2)
    np.testing.assert_array_equal(again.tets, mesh.tets)
    finer = solver.load_mesh(path, mesher="tetwild", edge_length=0.02, fit=0.2)
    assert finer.n_tets > 2 * mesh.n_tets
    assert len(os.listdir(tmp_path / "cache")) == 2


def test_voxelised_bunny_is_one_face_connected_body():
    # at resolution 8 two voxels of the bunny touch the rest only along an edge and two more float
    # free (issue 11); all four go
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "assets", "bunny.off")
    with pytest.warns(MeshWarning, match="dropped 4 of 103 voxels"):
        mesh = solver.load_mesh(path, resolution=8)
    assert mesh.n_tets == 618 - 4 * 6
    assert (face_components(mesh.tets) == 0).all()


@needs_tetwild
def test_remeshing_a_sliver_mesh_gives_well_shaped_tets_of_the_same_volume(tmp_path, monkeypatch):
    monkeypatch.setenv("VBD_CACHE_DIR", str(tmp_path))
    bad = solver.sliver_box_mesh()
    good = bad.remeshed(edge_length=0.05)
    assert good.quality().n_slivers == 0
    assert good.rest_volumes().sum() == pytest.approx(bad.rest_volumes().sum(), rel=0.02)
