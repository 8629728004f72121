"""Headless software renderer written in Taichi kernels.

The renderer draws the boundary triangles of one or more tet meshes into an RGB image:

1. ``_rasterise`` runs one thread per triangle. Each thread walks the pixels of its screen
   bounding box and keeps, per pixel, the smallest 64-bit key ``(view depth bits << 32) | triangle``
   with an atomic min. Positive float32 values order like their bit patterns, so the key is a
   z-buffer whose ties are broken by triangle index: the result does not depend on thread order,
   which makes every image bit-for-bit reproducible.
2. ``_background`` paints the sky gradient and the reference grid plane (the ground, or a back
   wall) procedurally, one ray-plane intersection per pixel. It depends only on the camera, the
   grid and the viewport, so it is computed once and reused while those stay the same.
3. ``_shade`` runs one thread per image row. Each pixel decodes its winning triangle, interpolates
   the vertex colours with perspective-correct barycentric weights and applies the triangle's light
   factor (the body replaces the background, so the grid needs no depth test), and blends a
   translucent, outlined "ghost" mesh (the reference solution) on top. Uncovered pixels copy the
   background.

Text, legends and panel borders are drawn afterwards with Pillow (see ``demo.compose``).
Buffers are allocated once per ``Renderer``; the kernels take ndarray arguments, so they are
compiled once per process whatever the mesh sizes are.
"""
from dataclasses import dataclass

import numpy as np

import solver
from solver._ti import ti

EMPTY_KEY = np.iinfo(np.int64).max
NEAR_PLANE = 1e-3


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: eye position, point looked at, up direction, vertical field of view."""

    eye: tuple = (0.5, -3.0, 0.0)
    target: tuple = (0.5, 0.0, 0.0)
    up: tuple = (0.0, 0.0, 1.0)
    fov_degrees: float = 40.0

    def basis(self):
        """Orthonormal (right, up, forward) rows of the view frame."""
        eye, target = np.asarray(self.eye, float), np.asarray(self.target, float)
        forward = target - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, np.asarray(self.up, float))
        right /= np.linalg.norm(right)
        return np.stack([right, np.cross(right, forward), forward])


@dataclass(frozen=True)
class GridPlane:
    """A reference plane drawn with grid lines: ``point`` on it, unit ``normal``, line ``spacing``."""

    point: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, 1.0)
    spacing: float = 0.1


@dataclass(frozen=True)
class Viewport:
    """Pixel rectangle of the image that one panel is drawn into."""

    x: int
    y: int
    width: int
    height: int


BACKGROUND_TOP = (0.93, 0.94, 0.96)
BACKGROUND_BOTTOM = (0.78, 0.80, 0.84)
GRID_RGB = (0.55, 0.57, 0.62)
GHOST_RGB = (0.95, 0.35, 0.25)
GHOST_ALPHA = 0.35
LIGHT_DIRECTION_TUPLE = tuple(float(v) for v in np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76]))


@ti.kernel
def _clear(key: ti.types.ndarray(dtype=ti.i64, ndim=2), x0: ti.i32, y0: ti.i32, x1: ti.i32, y1: ti.i32):
    for r, c in ti.ndrange((y0, y1), (x0, x1)):
        key[r, c] = ti.i64(9223372036854775807)


@ti.kernel
def _project(positions: ti.types.ndarray(dtype=ti.f64, ndim=2), faces: ti.types.ndarray(dtype=ti.i32, ndim=2),
             frame: ti.types.ndarray(dtype=ti.f32, ndim=2), focal: ti.f32, cx: ti.f32, cy: ti.f32,
             screen: ti.types.ndarray(dtype=ti.f32, ndim=2), light: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    """Screen (column, row, view depth) per vertex and a light factor per face."""
    eye = ti.Vector([frame[3, 0], frame[3, 1], frame[3, 2]])
    right = ti.Vector([frame[0, 0], frame[0, 1], frame[0, 2]])
    up = ti.Vector([frame[1, 0], frame[1, 1], frame[1, 2]])
    forward = ti.Vector([frame[2, 0], frame[2, 1], frame[2, 2]])
    for v in range(positions.shape[0]):
        d = ti.Vector([positions[v, 0], positions[v, 1], positions[v, 2]], ti.f32) - eye
        z = d.dot(forward)
        screen[v, 0] = ti.cast(cx + focal * d.dot(right) / ti.max(z, 1e-9), ti.f32)
        screen[v, 1] = ti.cast(cy - focal * d.dot(up) / ti.max(z, 1e-9), ti.f32)
        screen[v, 2] = z
    sun = ti.Vector(LIGHT_DIRECTION_TUPLE)
    for f in range(faces.shape[0]):
        p0 = ti.Vector([positions[faces[f, 0], j] for j in ti.static(range(3))], ti.f32)
        p1 = ti.Vector([positions[faces[f, 1], j] for j in ti.static(range(3))], ti.f32)
        p2 = ti.Vector([positions[faces[f, 2], j] for j in ti.static(range(3))], ti.f32)
        n = (p1 - p0).cross(p2 - p0)
        n = ti.cast(n / ti.max(n.norm(), 1e-30), ti.f32)
        if n.dot(eye - (p0 + p1 + p2) / 3.0) < 0.0:     # light both sides: face the camera
            n = -n
        light[f] = ti.cast(0.30 + 0.45 * ti.max(n.dot(sun), 0.0) + 0.30 * ti.max(-n.dot(forward), 0.0), ti.f32)


@ti.func
def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@ti.kernel
def _rasterise(screen: ti.types.ndarray(dtype=ti.f32, ndim=2), faces: ti.types.ndarray(dtype=ti.i32, ndim=2),
               key: ti.types.ndarray(dtype=ti.i64, ndim=2), x0: ti.i32, y0: ti.i32, x1: ti.i32, y1: ti.i32):
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay, az = screen[a, 0], screen[a, 1], screen[a, 2]
        bx, by, bz = screen[b, 0], screen[b, 1], screen[b, 2]
        cx, cy, cz = screen[c, 0], screen[c, 1], screen[c, 2]
        area = _edge(ax, ay, bx, by, cx, cy)
        if az > NEAR_PLANE and bz > NEAR_PLANE and cz > NEAR_PLANE and ti.abs(area) > 1e-12:
            lo_c = ti.max(x0, ti.cast(ti.floor(ti.min(ax, bx, cx)), ti.i32))
            hi_c = ti.min(x1 - 1, ti.cast(ti.ceil(ti.max(ax, bx, cx)), ti.i32))
            lo_r = ti.max(y0, ti.cast(ti.floor(ti.min(ay, by, cy)), ti.i32))
            hi_r = ti.min(y1 - 1, ti.cast(ti.ceil(ti.max(ay, by, cy)), ti.i32))
            inv_area = 1.0 / area
            for r in range(lo_r, hi_r + 1):
                py = ti.cast(r, ti.f32) + 0.5
                for col in range(lo_c, hi_c + 1):
                    px = ti.cast(col, ti.f32) + 0.5
                    wa = _edge(bx, by, cx, cy, px, py) * inv_area
                    wb = _edge(cx, cy, ax, ay, px, py) * inv_area
                    wc = 1.0 - wa - wb
                    if wa >= 0.0 and wb >= 0.0 and wc >= 0.0:
                        inv_depth = wa / az + wb / bz + wc / cz
                        depth = ti.cast(1.0 / inv_depth, ti.f32)
                        k = (ti.cast(ti.bit_cast(depth, ti.i32), ti.i64) << 32) | ti.cast(f, ti.i64)
                        ti.atomic_min(key[r, col], k)


@ti.func
def _corner_weights(screen: ti.template(), faces: ti.template(), f, px, py):
    """Perspective-correct barycentric weights of pixel (px, py) in triangle f."""
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    ax, ay, az = screen[a, 0], screen[a, 1], screen[a, 2]
    bx, by, bz = screen[b, 0], screen[b, 1], screen[b, 2]
    cx, cy, cz = screen[c, 0], screen[c, 1], screen[c, 2]
    inv_area = 1.0 / _edge(ax, ay, bx, by, cx, cy)
    wa = _edge(bx, by, cx, cy, px, py) * inv_area / az
    wb = _edge(cx, cy, ax, ay, px, py) * inv_area / bz
    wc = (1.0 - _edge(bx, by, cx, cy, px, py) * inv_area - _edge(cx, cy, ax, ay, px, py) * inv_area) / cz
    s = wa + wb + wc
    return ti.Vector([wa / s, wb / s, wc / s])


@ti.func
def _decode_depth(k):
    return ti.bit_cast(ti.cast(k >> 32, ti.i32), ti.f32)


@ti.kernel
def _background(background: ti.types.ndarray(dtype=ti.u8, ndim=3), frame: ti.types.ndarray(dtype=ti.f32, ndim=2),
                focal: ti.f32, grid: ti.types.ndarray(dtype=ti.f32, ndim=1), has_grid: ti.i32,
                x0: ti.i32, y0: ti.i32, x1: ti.i32, y1: ti.i32):
    """The vertical gradient and, procedurally per pixel, the grid plane (a ray-plane intersection).

    It depends only on the camera, the grid and the viewport, so ``Renderer`` computes it once and
    keeps it while those stay the same. Where the body covers a pixel it replaces this colour, so
    the grid needs no depth test against the body.
    """
    cx = ti.f32(0.5) * ti.cast(x0 + x1, ti.f32)
    cy = ti.f32(0.5) * ti.cast(y0 + y1, ti.f32)
    eye = ti.Vector([frame[3, 0], frame[3, 1], frame[3, 2]])
    right = ti.Vector([frame[0, 0], frame[0, 1], frame[0, 2]])
    up = ti.Vector([frame[1, 0], frame[1, 1], frame[1, 2]])
    forward = ti.Vector([frame[2, 0], frame[2, 1], frame[2, 2]])
    top = ti.Vector([BACKGROUND_TOP[0], BACKGROUND_TOP[1], BACKGROUND_TOP[2]], ti.f32)
    bottom = ti.Vector([BACKGROUND_BOTTOM[0], BACKGROUND_BOTTOM[1], BACKGROUND_BOTTOM[2]], ti.f32)
    grid_rgb = ti.Vector(GRID_RGB, ti.f32)
    normal = ti.Vector([grid[3], grid[4], grid[5]])
    point = ti.Vector([grid[0], grid[1], grid[2]])
    spacing = grid[6]
    plane = (point - eye).dot(normal)
    for r in range(y0, y1):     # one thread per row, columns in order
        py = ti.cast(r, ti.f32) + ti.f32(0.5)
        t = (py - ti.cast(y0, ti.f32)) / ti.cast(y1 - y0, ti.f32)
        sky = top * (1.0 - t) + bottom * t
        for c in range(x0, x1):
            px = ti.cast(c, ti.f32) + ti.f32(0.5)
            rgb = sky
            if has_grid != 0:
                ray = forward + right * ((px - cx) / focal) - up * ((py - cy) / focal)
                denom = ray.dot(normal)
                if ti.abs(denom) > 1e-6:
                    s = plane / denom
                    if s > 0.0:
                        hit = eye + ray * s
                        # line width grows with distance so lines stay about one pixel wide
                        width = ti.cast(1.2, ti.f32) * s / focal
                        line = ti.cast(0.0, ti.f32)
                        for d in ti.static(range(3)):
                            if ti.abs(normal[d]) < 0.5:
                                u = hit[d] / spacing
                                dist = ti.abs(u - ti.round(u)) * spacing
                                line = ti.max(line, ti.max(ti.f32(0.0), ti.f32(1.0) - dist / width))
                        a = ti.cast(0.6, ti.f32) * line / (1.0 + ti.cast(0.3, ti.f32) * s)
                        rgb = sky * (1.0 - a) + grid_rgb * a
            for j in ti.static(range(3)):
                background[r, c, j] = ti.cast(ti.min(255.0, ti.max(0.0, rgb[j] * 255.0 + 0.5)), ti.u8)


@ti.kernel
def _shade(image: ti.types.ndarray(dtype=ti.u8, ndim=3), background: ti.types.ndarray(dtype=ti.u8, ndim=3),
           key: ti.types.ndarray(dtype=ti.i64, ndim=2),
           screen: ti.types.ndarray(dtype=ti.f32, ndim=2), faces: ti.types.ndarray(dtype=ti.i32, ndim=2),
           vertex_rgb: ti.types.ndarray(dtype=ti.f32, ndim=2), light: ti.types.ndarray(dtype=ti.f32, ndim=1),
           ghost_key: ti.types.ndarray(dtype=ti.i64, ndim=2), ghost_light: ti.types.ndarray(dtype=ti.f32, ndim=1),
           has_ghost: ti.i32, nearest: ti.i32, x0: ti.i32, y0: ti.i32, x1: ti.i32, y1: ti.i32):
    # one thread per row, columns in order: cheaper on the CPU than a flattened 2D range
    empty = ti.i64(9223372036854775807)
    for r in range(y0, y1):
        py = ti.cast(r, ti.f32) + 0.5
        for c in range(x0, x1):
            k = key[r, c]
            g = empty
            if has_ghost != 0:
                g = ghost_key[r, c]
            if k == empty and g == empty:
                for j in ti.static(range(3)):
                    image[r, c, j] = background[r, c, j]
            else:
                px = ti.cast(c, ti.f32) + 0.5
                rgb = ti.Vector([ti.cast(background[r, c, j], ti.f32) for j in ti.static(range(3))]) / 255.0
                if k != empty:
                    key[r, c] = empty    # ready for the next draw
                    f = ti.cast(k & ti.i64(0xFFFFFFFF), ti.i32)
                    w = _corner_weights(screen, faces, f, px, py)
                    if nearest != 0:
                        # each pixel takes the colour of the nearest corner: vertices become patches
                        best = 0
                        if w[1] > w[best]:
                            best = 1
                        if w[2] > w[best]:
                            best = 2
                        w = ti.Vector([0.0, 0.0, 0.0])
                        w[best] = 1.0
                    base = ti.Vector([0.0, 0.0, 0.0])
                    for j in ti.static(range(3)):
                        v = faces[f, j]
                        base += w[j] * ti.Vector([vertex_rgb[v, 0], vertex_rgb[v, 1], vertex_rgb[v, 2]])
                    rgb = base * light[f]
                if g != empty:
                    gf = ti.cast(g & ti.i64(0xFFFFFFFF), ti.i32)
                    ghost = ti.Vector(GHOST_RGB) * ghost_light[gf]
                    edge = 0
                    if r > y0 and r < y1 - 1 and c > x0 and c < x1 - 1:
                        if ghost_key[r - 1, c] == empty or ghost_key[r + 1, c] == empty or \
                                ghost_key[r, c - 1] == empty or ghost_key[r, c + 1] == empty:
                            edge = 1
                    if edge == 1:
                        rgb = ti.Vector(GHOST_RGB) * 0.8
                    elif k == empty:
                        # translucent where the body is not; over the body only the outline shows
                        rgb = rgb * (1.0 - GHOST_ALPHA) + ghost * GHOST_ALPHA
                for j in ti.static(range(3)):
                    image[r, c, j] = ti.cast(ti.min(255.0, ti.max(0.0, rgb[j] * 255.0 + 0.5)), ti.u8)


@dataclass
class Body:
    """What to draw for one panel: vertex positions, boundary faces and per-vertex RGB in [0, 1]."""

    positions: np.ndarray
    faces: np.ndarray
    rgb: np.ndarray
    ghost_positions: np.ndarray = None
    nearest_vertex: bool = False    # paint each pixel with its nearest corner's colour (no blending)


class Renderer:
    """Draws bodies into a fixed-size RGB image. Allocate one per image size and reuse it."""

    def __init__(self, width, height, arch="cpu"):
        solver.ensure_taichi(arch=arch)
        self.width, self.height = int(width), int(height)
        self._key = ti.ndarray(ti.i64, shape=(self.height, self.width))
        self._ghost_key = ti.ndarray(ti.i64, shape=(self.height, self.width))
        # a NumPy image is written in place by the CPU backend (no copy back)
        self._image = np.zeros((self.height, self.width, 3), np.uint8)
        self._background = np.zeros((self.height, self.width, 3), np.uint8)
        self._background_of = {}    # viewport box -> (camera frame, focal, grid) its background was drawn for
        self._scratch = {}
        _clear(self._key, 0, 0, self.width, self.height)
        self._no_light = np.zeros(1, np.float32)
        self._no_grid = np.zeros(7, np.float32)

    def draw(self, body, camera, viewport=None, grid=None, framed=None):
        """Draw ``body`` seen from ``camera`` into ``viewport`` (default: the whole image); ``framed``: see
        `focal_length`."""
        vp = viewport or Viewport(0, 0, self.width, self.height)
        box = (vp.x, vp.y, vp.x + vp.width, vp.y + vp.height)
        basis = camera.basis()
        eye = np.asarray(camera.eye, float)
        focal = self.focal_length(camera, vp, framed)
        centre = (vp.x + 0.5 * vp.width, vp.y + 0.5 * vp.height)
        faces = np.ascontiguousarray(body.faces, dtype=np.int32)

        frame = np.vstack([basis, eye]).astype(np.float32)
        screen, light = self._buffers("body", len(body.positions), len(faces))
        _project(np.ascontiguousarray(body.positions, dtype=np.float64), faces, frame, focal, *centre, screen, light)
        _rasterise(screen, faces, self._key, *box)
        has_ghost = body.ghost_positions is not None
        ghost_light = self._no_light
        if has_ghost:
            ghost_screen, ghost_light = self._buffers("ghost", len(body.ghost_positions), len(faces))
            _project(np.ascontiguousarray(body.ghost_positions, dtype=np.float64), faces, frame, focal, *centre,
                     ghost_screen, ghost_light)
            _clear(self._ghost_key, *box)
            _rasterise(ghost_screen, faces, self._ghost_key, *box)
        self._ensure_background(box, frame, focal, grid)
        vertex_rgb = np.ascontiguousarray(body.rgb, dtype=np.float32)
        _shade(self._image, self._background, self._key, screen, faces, vertex_rgb, light, self._ghost_key, ghost_light,
               int(has_ghost), int(body.nearest_vertex), *box)

    @staticmethod
    def focal_length(camera, viewport, framed=None):
        """Pixels per unit of (sideways / forward) distance from the eye: the camera's vertical field of
        view spans the viewport's height. With ``framed``, the (width, height) of the viewport the camera
        was chosen for, a viewport narrower than that shape is fitted by its width instead, so that it shows
        at least all that one showed (a portrait frame keeps the bodies that fill a landscape one)."""
        focal = 0.5 * viewport.height / np.tan(np.radians(camera.fov_degrees) / 2)
        if framed is not None and viewport.width * framed[1] < framed[0] * viewport.height:
            focal *= viewport.width * framed[1] / (framed[0] * viewport.height)
        return focal

    def forget_background(self):
        """Drop the cached gradient + grid, so the next draw recomputes it (benchmarks use this)."""
        self._background_of = {}

    def _ensure_background(self, box, frame, focal, grid):
        """Gradient + grid of a viewport, recomputed only when its camera, grid or box changes."""
        signature = (frame.tobytes(), float(focal), grid)
        if self._background_of.get(box) == signature:
            return
        grid_data = self._no_grid
        if grid is not None:
            normal = np.asarray(grid.normal, float) / np.linalg.norm(grid.normal)
            grid_data = np.array([*grid.point, *normal, grid.spacing], np.float32)
        _background(self._background, frame, float(focal), grid_data, int(grid is not None), *box)
        x0, y0, x1, y1 = box
        # a viewport drawn over another one invalidates the other's cached background
        self._background_of = {b: sig for b, sig in self._background_of.items()
                               if b[2] <= x0 or x1 <= b[0] or b[3] <= y0 or y1 <= b[1]}
        self._background_of[box] = signature

    def image(self):
        """A copy of the current image as an (height, width, 3) uint8 array."""
        return self._image.copy()

    def _buffers(self, name, n_vertices, n_faces):
        """Per-vertex screen and per-face light arrays, reused while the mesh size stays the same."""
        screen, light = self._scratch.get(name, (None, None))
        if screen is None or len(screen) != n_vertices or len(light) != n_faces:
            screen, light = np.empty((n_vertices, 3), np.float32), np.empty(n_faces, np.float32)
            self._scratch[name] = (screen, light)
        return screen, light
