"""The Taichi rasteriser: deterministic, and the object is where the camera says."""
import numpy as np
import pytest

import solver
from demo import colors
from demo.compose import FrameComposer
from demo.render import Body, Camera, GridPlane, Renderer, Viewport
from demo.runner import SceneRunner
from demo import scenes

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA

# row 0 of the background gradient (top colour blended 0.5/48 of the way towards the bottom colour)
BACKGROUND_ROW0 = np.floor((np.array([0.93, 0.94, 0.96]) * (1 - 1 / 96) + np.array([0.78, 0.80, 0.84]) / 96) * 255 + 0.5)


@pytest.fixture(scope="module")
def bar():
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(4, 1, 1))
    return mesh.vertices, mesh.boundary_faces()


def draw(bar, camera, width=64, height=48, ghost=None, grid=None):
    vertices, faces = bar
    renderer = Renderer(width, height)
    renderer.draw(Body(vertices, faces, colors.uniform(len(vertices), (1.0, 1.0, 1.0)), ghost), camera, grid=grid)
    return renderer.image()


def test_tiny_render_is_pixel_deterministic(bar):
    camera = Camera(eye=(0.5, -2.0, 0.05), target=(0.5, 0.0, 0.05), fov_degrees=40)
    ghost = bar[0] + (0.0, 0.0, -0.05)
    first = draw(bar, camera, ghost=ghost, grid=GridPlane())
    again = draw(bar, camera, ghost=ghost, grid=GridPlane())
    assert first.shape == (48, 64, 3) and first.dtype == np.uint8
    np.testing.assert_array_equal(first, again)


def test_object_is_where_the_camera_looks(bar):
    image = draw(bar, Camera(eye=(0.5, -2.0, 0.05), target=(0.5, 0.0, 0.05), fov_degrees=40))
    # the front face (normal -y) faces the camera: light = ambient + diffuse + headlight
    light_dir = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])
    expected = round(255 * (0.30 + 0.45 * light_dir[1] * -1 + 0.30))
    assert np.abs(image[24, 32].astype(int) - expected).max() <= 1
    # the bar is 1 m long and 0.1 m tall, seen from 2 m with focal 24 / tan(20 deg) = 65.9 px:
    # columns 32 -+ 0.5 / 2 * 65.9 = 15.5 .. 48.5; the front face spans rows 24 -+ 1.6
    covered = (image == expected).all(axis=2) | (np.abs(image.astype(int) - expected).max(axis=2) <= 1)
    rows, cols = np.nonzero(covered)
    assert 21 <= rows.min() and rows.max() <= 27
    assert cols.min() in (15, 16) and cols.max() in (47, 48)
    # nothing in the corners but background
    np.testing.assert_array_equal(image[0, 0], BACKGROUND_ROW0)


def test_camera_looking_away_sees_only_background(bar):
    image = draw(bar, Camera(eye=(0.5, -2.0, 0.05), target=(0.5, -4.0, 0.05), fov_degrees=40))
    assert (np.abs(np.diff(image[:, 32].astype(int), axis=0)) <= 1).all()    # a smooth gradient, no body


def test_ghost_and_viewports(bar):
    camera = Camera(eye=(0.5, -2.0, 0.05), target=(0.5, 0.0, 0.05), fov_degrees=40)
    plain = draw(bar, camera)
    with_ghost = draw(bar, camera, ghost=bar[0] + (0.0, 0.0, -0.12))
    assert (plain != with_ghost).any(axis=2).sum() > 50
    vertices, faces = bar
    renderer = Renderer(64, 48)
    body = Body(vertices, faces, colors.uniform(len(vertices)))
    renderer.draw(body, camera, Viewport(0, 0, 32, 48))
    renderer.draw(body, camera, Viewport(32, 0, 32, 48))
    image = renderer.image()
    np.testing.assert_array_equal(image[:, :32], image[:, 32:])


def test_cached_background_follows_the_camera(bar):
    """The gradient + grid is cached per viewport; a new camera or grid must redraw it."""
    near = Camera(eye=(0.5, -2.0, 0.05), target=(0.5, 0.0, 0.05), fov_degrees=40)
    far = Camera(eye=(0.5, -3.0, 0.6), target=(0.5, 0.0, 0.0), fov_degrees=50)
    vertices, faces = bar
    body = Body(vertices, faces, colors.uniform(len(vertices)))
    reused = Renderer(64, 48)
    reused.draw(body, near, grid=GridPlane())
    reused.draw(body, far, grid=GridPlane(spacing=0.05))
    fresh = Renderer(64, 48)
    fresh.draw(body, far, grid=GridPlane(spacing=0.05))
    np.testing.assert_array_equal(reused.image(), fresh.image())
    reused.draw(body, far)      # no grid any more
    plain = Renderer(64, 48)
    plain.draw(body, far)
    np.testing.assert_array_equal(reused.image(), plain.image())


def test_composed_frame_has_labels_and_is_deterministic():
    scene = scenes.get("colouring")
    states = SceneRunner(scene).advance()
    a = np.asarray(FrameComposer(scene, 160, 96).compose(states))
    b = np.asarray(FrameComposer(scene, 160, 96).compose(states))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (96, 160, 3)
    assert len(np.unique(a.reshape(-1, 3), axis=0)) > 20      # colour sets, text, background
    assert states[0].lines[1].endswith("vertices") and "colours" in states[0].lines[1]
