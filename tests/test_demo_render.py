"""The Taichi rasteriser: deterministic, and the object is where the camera says."""
import dataclasses

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


@pytest.fixture(scope="module")
def first_states():
    """The first frame's panel states of a scene, by name (simulated once per module)."""
    cache = {}

    def states(name):
        if name not in cache:
            cache[name] = SceneRunner(scenes.get(name)).advance()
        return cache[name]
    return states


TEXT_SIZES = [(1280, 720), (800, 800), (640, 480), (640, 1200), (320, 180), (200, 300), (64, 48), (48, 32),
              (16, 16)]


@pytest.mark.parametrize("name", ["real_shapes", "stiffness_sweep", "propagation"])
def test_every_piece_of_text_lies_inside_the_frame(first_states, name):
    """The title and the notes were drawn unwrapped: at 800x800 real_shapes' title ended '...without kee', at
    640x480 stiffness_sweep's ghost note ran off the right edge. Now they are wrapped to the width (each row
    within it, as the composer measures it), and where half the height cannot hold them all the last row
    kept ends in ' ...'; the labels stay in their panels, the colour legend (propagation) inside the frame."""
    scene = scenes.get(name)
    band_text = " ".join([scene.title, *scene.notes]).split()
    for width, height in TEXT_SIZES:
        composer = FrameComposer(scene, width, height)
        composer.compose(first_states(name))
        inside = lambda b: 0 <= b[0] and 0 <= b[1] and b[2] <= width and b[3] <= height
        assert all(inside(b) for b in composer.text_boxes), (width, height)
        assert composer.title_band <= height // 2
        rows = [text for text, *_ in composer.title_rows]
        title_boxes = composer.text_boxes[:len(rows)]
        assert all(b[3] <= composer.title_band for b in title_boxes), (width, height)
        shown = " ".join(rows).split()
        if not rows:
            assert composer.title_band == 0 and height < 40, (width, height)     # no room for one row
        elif rows[-1].endswith(" ..."):
            assert shown[:-2] == band_text[:len(shown) - 2], (width, height)
        else:
            assert shown == band_text, (width, height)      # nothing lost
        for label in composer.label_boxes:
            assert any(p.x <= label[0] and label[2] <= p.x + p.width for p in composer.panels), (width, height)
            assert composer.title_band <= label[1] and label[3] <= composer.title_band + composer.label_band
    big = FrameComposer(scene, 800, 800)
    assert not big.title_rows[-1][0].endswith(" ...")        # 800x800 shows the whole title and every note


def test_a_frame_drawn_from_what_the_composer_kept_is_the_frame_drawn_afresh():
    """The composer draws the title band once and pastes it into later frames, and remembers each label's
    pieces and each text's box: a second frame with other labels (the error line changes from frame to
    frame) is, pixel for pixel and box for box, what a new composer draws for it."""
    scene = scenes.get("stiffness_sweep")
    runner = SceneRunner(scene)
    first, second = runner.advance(), runner.advance()
    assert [s.lines for s in first] != [s.lines for s in second]
    kept = FrameComposer(scene, 640, 360)
    kept.compose(first)
    again = kept.compose(second)
    fresh = FrameComposer(scene, 640, 360)
    expected = fresh.compose(second)
    np.testing.assert_array_equal(np.asarray(again), np.asarray(expected))
    assert kept.text_boxes == fresh.text_boxes and kept.label_boxes == fresh.label_boxes
    assert kept.title_band > 0 and len(kept.text_boxes) > len(kept.title_rows)


def test_fit_breaks_lines_and_words_to_the_width():
    composer = FrameComposer(scenes.get("twist"), 64, 48)
    pieces = composer.fit("a Verylongunbreakableword and more", 30)
    assert all(composer.font.getlength(p) <= 30 for p in pieces) and len(pieces) > 3
    assert "".join(p.strip() for p in pieces) == "aVerylongunbreakablewordandmore"
    assert composer.fit("wide", 1) == []                    # not one letter fits
    assert composer.shortened("a line too long to fit", 40, composer.font).endswith(" ...")
    assert composer.font.getlength(composer.shortened("a line too long to fit", 40, composer.font)) <= 40


@pytest.mark.parametrize("name", ["real_shapes", "stiffness_sweep"])
def test_bodies_fit_their_panels_at_any_shape(first_states, name):
    """The focal length came from the vertical field of view alone, so a panel narrower than at the default
    size cut the bodies off at its sides (640x1200: the bunnies' tails and the cow). Now a panel narrower
    than its default-size shape is fitted by its width: every body projects inside its viewport, and the
    drawn pixels (the bodies painted plain green) are where that projection says."""
    scene = scenes.get(name)
    green = [dataclasses.replace(s, rgb=np.tile([0.0, 1.0, 0.0], (len(s.positions), 1)), ghost=None)
             for s in first_states(name)]
    basis, eye = scene.camera.basis(), np.asarray(scene.camera.eye)
    for width, height in [(1280, 720), (640, 1200), (800, 800), (160, 400), (320, 180), (1280, 300)]:
        composer = FrameComposer(scene, width, height)
        image = np.asarray(composer.compose(green)).astype(int)
        body = (image[..., 1] > 50) & (image[..., 0] < 10) & (image[..., 2] < 10)
        for state, vp, framed in zip(green, composer.viewports, composer.framed):
            d = (state.positions - eye) @ basis.T
            focal = Renderer.focal_length(scene.camera, vp, framed)
            col = vp.x + 0.5 * vp.width + focal * d[:, 0] / d[:, 2]
            row = vp.y + 0.5 * vp.height - focal * d[:, 1] / d[:, 2]
            assert vp.x < col.min() and col.max() < vp.x + vp.width, (width, height, vp)
            assert vp.y < row.min() and row.max() < vp.y + vp.height, (width, height, vp)
            rows, cols = np.nonzero(body[vp.y:vp.y + vp.height, vp.x:vp.x + vp.width])
            drawn = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1]) + [vp.x, vp.y, vp.x, vp.y]
            projected = np.array([col.min(), row.min(), col.max(), row.max()])
            assert np.abs(drawn - projected).max() <= 1.5, (width, height, drawn, projected)
