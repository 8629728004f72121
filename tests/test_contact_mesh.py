"""Several bodies in one mesh (solver/mesh/bodies.py, surface.py): merging, body labels, surface primitives."""
import numpy as np
import pytest

import solver
from solver.mesh.bodies import body_labels
from solver.mesh.surface import surface_primitives


def test_merge_keeps_vertices_in_order_and_renumbers_tets():
    a = solver.box_mesh(size=(1, 1, 1), cells=(2, 1, 1))
    b = solver.box_mesh(size=(0.5, 0.5, 0.5), cells=(1, 1, 1))
    merged = solver.merge_meshes([a, solver.TetMesh(b.vertices + 3.0, b.tets)])
    assert merged.n_vertices == a.n_vertices + b.n_vertices and merged.n_tets == a.n_tets + b.n_tets
    np.testing.assert_array_equal(merged.vertices[:a.n_vertices], a.vertices)
    np.testing.assert_array_equal(merged.vertices[a.n_vertices:], b.vertices + 3.0)
    np.testing.assert_array_equal(merged.tets[:a.n_tets], a.tets)
    np.testing.assert_array_equal(merged.tets[a.n_tets:], b.tets + a.n_vertices)
    assert merged.rest_volumes().sum() == pytest.approx(a.rest_volumes().sum() + b.rest_volumes().sum())


@pytest.mark.parametrize("bad", [[], None, "mesh", [np.zeros((4, 3))]])
def test_merge_refuses_what_is_not_a_list_of_meshes(bad):
    with pytest.raises(solver.MeshError) as err:
        solver.merge_meshes(bad)
    assert "\n" not in str(err.value)


def test_a_single_mesh_is_refused_with_the_fix():
    with pytest.raises(solver.MeshError, match=r"merge_meshes\(\[mesh_a, mesh_b\]\)"):
        solver.merge_meshes(solver.box_mesh(size=(1, 1, 1), cells=(1, 1, 1)))


def test_meshes_passed_one_by_one_are_refused_with_the_fix():
    a = solver.box_mesh(size=(1, 1, 1), cells=(1, 1, 1))
    b = solver.TetMesh(a.vertices + 3.0, a.tets)
    with pytest.raises(solver.MeshError, match=r"got 2 arguments; pass a list: merge_meshes\(\[a, b\]\)") as err:
        solver.merge_meshes(a, b)
    assert "\n" not in str(err.value)


def test_bodies_are_vertex_components_numbered_by_their_smallest_vertex():
    cube = solver.box_mesh(size=(1, 1, 1), cells=(1, 1, 1))
    # three cubes; the third's vertices are listed first, so it is body 0
    third = cube.vertices + [0, 0, 5.0]
    vertices = np.concatenate([third, cube.vertices, cube.vertices + [2.0, 0, 0]])
    n = len(cube.vertices)
    tets = np.concatenate([cube.tets + n, cube.tets + 2 * n, cube.tets])
    labels = body_labels(tets, 3 * n)
    assert labels.dtype == np.int32
    np.testing.assert_array_equal(labels, np.repeat([0, 1, 2], n))
    # two tets sharing only a vertex are one body
    touching = np.array([[0, 1, 2, 3], [3, 4, 5, 6]])
    np.testing.assert_array_equal(body_labels(touching, 7), np.zeros(7))


def test_surface_primitives_of_a_cube():
    mesh = solver.box_mesh(size=(1, 1, 1), cells=(2, 2, 2))
    s = surface_primitives(mesh.tets)
    assert len(s.triangles) == 6 * 4 * 2                                 # 2 triangles per face cell
    assert len(s.vertices) == 27 - 1                                      # all but the centre
    assert len(s.vertices) - len(s.edges) + len(s.triangles) == 2         # Euler: a closed sphere-like surface
    assert (s.edges[:, 0] < s.edges[:, 1]).all()
    assert len(np.unique(s.edges, axis=0)) == len(s.edges)
    np.testing.assert_array_equal(s.vertices, np.unique(s.triangles))
    with pytest.raises(ValueError):
        s.edges[0, 0] = 5


def test_the_crossing_judge_sees_a_vertex_pushed_through_a_face():
    from contact_checks import crossings

    cube = solver.box_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2))
    apart = solver.merge_meshes([cube, solver.TetMesh(cube.vertices + [0.03, 0.02, 0.101], cube.tets)])
    assert len(crossings(apart.vertices, apart.tets)[0]) == 0
    x = apart.vertices.copy()
    # the top cube's bottom-centre vertex 1 cm down, through the lower cube's top face
    bottom_centre = np.flatnonzero(np.all(np.isclose(apart.vertices, [0.08, 0.07, 0.101]), axis=1))
    x[bottom_centre] -= [0, 0, 0.01]
    found, edges, triangles = crossings(x, apart.tets)
    assert len(found) > 0
    # every crossing involves the pushed vertex: its edges through the lower top face, or the lower
    # top face's edges through the triangles around it
    assert all(bottom_centre[0] in edges[e] or bottom_centre[0] in triangles[t] for e, t in found)
    assert len(crossings(x - np.where(np.arange(len(x))[:, None] >= cube.n_vertices, [0, 0, -0.02], 0),
                         apart.tets)[0]) == 0
    # self contact: a cube's own surface folded through itself is judged only with self_contact
    folded = cube.vertices.copy()
    top_centre = np.flatnonzero(np.all(np.isclose(cube.vertices, [0.05, 0.05, 0.1]), axis=1))
    folded[top_centre] = [0.05, 0.05, -0.02]
    assert len(crossings(folded, cube.tets)[0]) > 0
    assert len(crossings(folded, cube.tets, self_contact=False)[0]) == 0


def _random_boxes(rng, n, scale):
    lo = rng.uniform(-1, 1, (n, 3))
    return lo, lo + rng.uniform(0, 1, (n, 3)) * scale


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("large", [64, 2])
def test_overlapping_boxes_finds_every_overlapping_pair_once(seed, large, monkeypatch):
    """The start-state check's candidates (`overlapping_boxes`) are exactly the brute-force overlapping pairs,
    each once and in order, also with boxes of very different sizes (a few large ones among many small,
    as a wall among balls, on both sides) and in chunks smaller than the result."""
    from solver.vbd import contact_state

    monkeypatch.setattr(contact_state, "PAIR_CHUNK", 7)
    monkeypatch.setattr(contact_state, "LARGE_BOXES", large)      # 2: the largest boxes outside the grid
    rng = np.random.default_rng(seed)
    lo_a, hi_a = _random_boxes(rng, 60, rng.choice([0.01, 0.1, 0.5]))
    lo_b, hi_b = _random_boxes(rng, 40, 0.05)
    lo_b[:3], hi_b[:3] = _random_boxes(rng, 3, 1.5)
    lo_a[:2], hi_a[:2] = _random_boxes(rng, 2, 2.0)
    overlap = ((lo_a[:, None] <= hi_b[None]) & (lo_b[None] <= hi_a[:, None])).all(axis=2)
    chunks = list(contact_state.overlapping_boxes(lo_a, hi_a, lo_b, hi_b))
    i, j = (np.concatenate([c[k] for c in chunks] + [np.zeros(0, np.int64)]) for k in (0, 1))
    assert all(len(c[0]) <= 7 for c in chunks)
    expected_i, expected_j = np.nonzero(overlap)
    np.testing.assert_array_equal(i, expected_i)
    np.testing.assert_array_equal(j, expected_j)


def test_boxes_within_finds_every_enclosed_box_of_a_moving_pair():
    from solver.vbd.contact_state import _boxes_within

    rng = np.random.default_rng(5)
    lower, upper = _random_boxes(rng, 300, 0.3)
    lower[:20], upper[:20] = lower[:20] - 0.5, upper[:20] + 0.5       # some large boxes holding small ones
    moving = rng.random(300) < 0.7
    within = (lower[:, None] >= lower[None]).all(axis=2) & (upper[:, None] <= upper[None]).all(axis=2)
    within &= (moving[:, None] | moving[None]) & ~np.eye(300, dtype=bool)
    inner, outer = _boxes_within(lower, upper, moving, rows=64)
    assert within.sum() > 20
    assert sorted(zip(inner.tolist(), outer.tolist())) == sorted(zip(*(k.tolist() for k in np.nonzero(within))))


def test_a_crossing_between_small_bodies_is_seen_beside_a_huge_one():
    """Whether a signed volume counts as coplanar is judged at the scale of the edge and triangle tested,
    not of the scene's longest edge: a 1,000 m slab (two triangles a face) hid two interpenetrating 1 cm
    cubes, one turned."""
    from scipy.spatial.transform import Rotation

    from solver.vbd.contact_state import surface_crossing

    slab = solver.box_mesh(size=(1000.0, 1000.0, 0.1), cells=(1, 1, 1), origin=(-500.0, -500.0, -0.1))
    a = solver.box_mesh(size=(0.01,) * 3, cells=(1, 1, 1), origin=(0.0, 0.0, 0.5))
    turn = Rotation.from_euler("xyz", [20, 30, 40], degrees=True).as_matrix()
    b = solver.TetMesh((a.vertices - [0.005, 0.005, 0.505]) @ turn.T + [0.004, 0.003, 0.505], a.tets)
    mesh = solver.merge_meshes([slab, a, b])
    free = np.arange(mesh.n_vertices) >= slab.n_vertices
    bodies = body_labels(mesh.tets, mesh.n_vertices)
    assert surface_crossing(mesh.vertices, surface_primitives(mesh.tets), bodies, free, True) == (1, 2)
