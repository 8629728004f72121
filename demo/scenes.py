"""The demo scenes, as data.

A ``Scene`` is a frozen description shared by the command line, the interactive window, the
benchmarks and the tests: which meshes, materials, pinned and scripted vertices, time step,
iteration budget, camera and length, and what the labels say. ``demo.runner`` turns one into
running simulations. A scene only asks for what it uses: ground contact, damping, Chebyshev
acceleration or a Newton reference ghost appear only where a scene sets them.

Scenes are side-by-side panels of one or more bodies. Every panel is its own ``solver.Simulation``
with its own settings, so a sweep is simply several panels that differ in one field.
"""
import enum
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import solver

from .errors import DemoError
from .render import Camera, GridPlane

REPO_ROOT = Path(__file__).resolve().parent.parent


class ColorBy(enum.Enum):
    """How vertices are coloured."""

    BODY = "body"                  # one flat colour per body (`colors.per_body`)
    DISPLACEMENT = "displacement"  # |x - x_n| in this time step, log scale
    RESIDUAL = "residual"          # |f_i|, the per-vertex force residual, log scale
    COLOR_SETS = "colour sets"    # the parallel colour of each vertex


class Advance(enum.Enum):
    """What one output frame shows."""

    TIME_STEPS = "time steps"    # one full time step per frame
    ITERATIONS = "iterations"    # one solver iteration of a single time step per frame
    COLOURS = "colours"          # one colour set of a VBD iteration per frame (the sweep, colour by colour)
    REST = "rest"                # nothing moves: the rest shape (needs only the mesh and its colouring)


class Sweep(enum.Enum):
    """How one iteration visits the vertices."""

    GAUSS_SEIDEL = "coloured Gauss-Seidel"   # colour after colour, each colour in parallel (VBD)
    JACOBI = "Jacobi"                        # every vertex at once, all from the same old positions


class Side(enum.Enum):
    LOW = "low"
    HIGH = "high"


@dataclass(frozen=True)
class BoxMesh:
    """A box of size (m) split into cells, each cell into tets."""

    size: tuple = (1.0, 0.1, 0.1)
    cells: tuple = (40, 4, 4)
    origin: tuple = (0.0, 0.0, 0.0)

    def build(self):
        return solver.box_mesh(size=self.size, cells=self.cells, origin=self.origin)


@dataclass(frozen=True)
class BallMesh:
    """A ball of radius (m) around the origin, cells (even) hexahedra per diameter (`solver.ball_mesh`)."""

    radius: float = 0.1
    cells: int = 4

    def build(self):
        return solver.ball_mesh(radius=self.radius, cells=self.cells)


@dataclass(frozen=True)
class AssetMesh:
    """A mesh file under the repository (a surface file is voxelised at ``resolution``), moved by ``offset`` (m)."""

    path: str
    resolution: int = None
    offset: tuple = (0.0, 0.0, 0.0)
    expect_slivers: bool = False    # the scene is about a mesh full of slivers: no quality warning

    def build(self):
        path = REPO_ROOT / self.path
        if not path.exists():
            raise DemoError(f"mesh asset {self.path} not found in this checkout; assets/make_assets.py makes it")
        with warnings.catch_warnings():
            if self.expect_slivers:     # the scene shows what slivers do; its description says so
                warnings.simplefilter("ignore", solver.MeshQualityWarning)
            if self.resolution is None:
                mesh = solver.load_mesh(str(path))
            else:
                mesh = solver.load_mesh(str(path), resolution=self.resolution)
        if any(self.offset):
            mesh = solver.TetMesh(mesh.vertices + np.asarray(self.offset, float), mesh.tets, mesh.original_index)
        return mesh


@dataclass(frozen=True)
class Bodies:
    """Several meshes as one ``solver.merge_meshes`` mesh, each moved by its offset (m); place them apart."""

    meshes: tuple
    offsets: tuple

    def build(self):
        built = [m.build() for m in self.meshes]
        return solver.merge_meshes([solver.TetMesh(m.vertices + np.asarray(o, float), m.tets)
                                    for m, o in zip(built, self.offsets)])


@dataclass(frozen=True)
class Outside:
    """The vertices not strictly inside the box [lower, upper] (m): the walls around a scene's bodies."""

    lower: tuple = (0.0, 0.0, 0.0)
    upper: tuple = (1.0, 1.0, np.inf)

    def select(self, vertices):
        inside = (vertices > np.asarray(self.lower)) & (vertices < np.asarray(self.upper))
        return ~inside.all(axis=1)


@dataclass(frozen=True)
class Approach:
    """Initial velocities: body 0 moves at +speed (m/s) along ``axis``, every other body at -speed."""

    speed: float = 1.0
    axis: int = 0

    def __call__(self, bodies):
        """(N, 3) velocities in m/s for the (N,) body number of each vertex."""
        v = np.zeros((len(bodies), 3))
        v[:, self.axis] = np.where(bodies == 0, self.speed, -self.speed)
        return v


@dataclass(frozen=True)
class EndFace:
    """The vertices on the lowest or highest face of the body along an axis (0 = x)."""

    axis: int = 0
    side: Side = Side.LOW

    def select(self, vertices):
        coord = vertices[:, self.axis]
        tol = 1e-6 * max(float(np.ptp(vertices)), 1e-12)
        end = coord.min() if self.side is Side.LOW else coord.max()
        return np.abs(coord - end) <= tol


@dataclass(frozen=True)
class Twist:
    """Scripted motion: the two ends of a bar turn in opposite directions about the bar's axis."""

    axis: int = 0
    degrees_per_second: float = 180.0

    def __call__(self, t, rest):
        centre = rest.mean(axis=0)
        sign = np.where(rest[:, self.axis] > centre[self.axis], 0.5, -0.5)
        angle = np.radians(self.degrees_per_second) * t * sign
        u, v = [d for d in range(3) if d != self.axis]
        du, dv = rest[:, u] - centre[u], rest[:, v] - centre[v]
        out = rest.copy()
        out[:, u] = centre[u] + np.cos(angle) * du - np.sin(angle) * dv
        out[:, v] = centre[v] + np.sin(angle) * du + np.cos(angle) * dv
        return out


@dataclass(frozen=True)
class Coil(Twist):
    """Scripted motion: a ``Twist`` whose two ends also move towards each other, each at ``approach`` (m/s)
    along the axis, so that the twisted bar buckles and coils onto itself."""

    approach: float = 0.1

    def __call__(self, t, rest):
        out = Twist.__call__(self, t, rest)
        centre = rest[:, self.axis].mean()
        out[:, self.axis] -= np.sign(rest[:, self.axis] - centre) * self.approach * t
        return out


@dataclass(frozen=True)
class Shift:
    """Scripted motion: jump by ``offset`` (m) at the first step and stay there."""

    offset: tuple = (0.0, 0.0, -0.05)

    def __call__(self, t, rest):
        return rest + (np.asarray(self.offset) if t > 0 else 0.0)


@dataclass(frozen=True)
class Panel:
    """One simulated body with its own material and solver settings, drawn in its own viewport."""

    label: str
    material: solver.Material
    mesh: object = BoxMesh()
    iterations: int = 20
    fixed: tuple = ()              # selectors (EndFace) of pinned vertices
    kinematic: tuple = ()          # selectors of scripted vertices
    motion: object = None          # callable(t, rest_positions) -> positions of the scripted vertices
    initial_guess: solver.InitialGuess = solver.InitialGuess.ADAPTIVE
    chebyshev_rho: float = None
    newton_ghost: bool = False     # draw the converged Newton solution of the same step
    show_drift: bool = False       # label how far the centre of mass has drifted across gravity
    keep_orientation: bool = False   # solver.Simulation(keep_orientation=...): no upright tet inverts
    show_inverted: bool = False    # label the number of inverted tets
    method: solver.Method = solver.Method.VBD    # solver.Simulation(method=...): the solver of each step
    # index of another panel of the scene: this (plain VBD) panel gets as many iterations per step as
    # fit in that panel's wall time per step, measured once when the scene starts (demo.runner)
    same_wall_time_as: int = None
    show_step_time: bool = False   # label the method, its budget and the measured wall time per step
    show_wave_cells: bool = False  # label N_c = h sqrt(E / rho) / dx, the cells an elastic wave crosses per step
    sweep: Sweep = Sweep.GAUSS_SEIDEL
    probe: tuple = ()              # selectors of the vertices whose one nearest the camera is highlighted and watched
    contact: solver.Contact = None     # solver.Simulation(contact=...): contact between bodies; labels its pairs
    velocity: object = None        # callable(bodies (N,)) -> (N, 3) initial velocities in m/s, e.g. Approach
    show_momentum: bool = False    # label the total momentum |sum m v| (kg m/s)


@dataclass(frozen=True)
class Scene:
    name: str
    title: str
    description: str
    panels: tuple
    camera: Camera
    dt: float = 1.0 / 60.0
    frames: int = 90
    fps: int = 30
    gravity: tuple = (0.0, 0.0, -9.81)
    ground: solver.Ground = None
    damping: float = 0.0
    grid: GridPlane = None
    color_by: ColorBy = ColorBy.BODY
    color_range: tuple = (1e-5, 1e-1)    # for DISPLACEMENT / RESIDUAL, log scale
    advance: Advance = Advance.TIME_STEPS
    notes: tuple = field(default=())      # extra lines printed under the title
    # the interactive window's Chebyshev slider stops here: above the spectral radius of the VBD
    # iteration the acceleration grows without bound (the soft and stiff bars of the sweeps fly off
    # at rho = 0.97-0.99 within a second; every scene stays put at 0.9 with 5 to 200 iterations)
    max_chebyshev_rho: float = 0.9


def _material(youngs_modulus):
    return solver.Material(youngs_modulus=youngs_modulus, poisson_ratio=0.3, density=1000.0)


PINNED_LEFT = (EndFace(0, Side.LOW),)
# a 0.5 m cantilever, 0.1 m square, 20 cells along: at E = 1e6 Pa the converged solution barely
# sags (a few cm) while 20 VBD iterations cannot carry the stiffness along 20 rings of elements
SHORT_BAR = BoxMesh(size=(0.5, 0.1, 0.1), cells=(20, 4, 4))
# frames x in [-0.05, 0.55] and z in [-1.0, 0.15]: the soft bar's whole swing, the stiff bar's sag
BAR_CAMERA = Camera(eye=(0.25, -2.35, -0.4), target=(0.25, 0.0, -0.4), fov_degrees=34.0)
BACK_WALL = GridPlane(point=(0.0, 0.4, 0.0), normal=(0.0, -1.0, 0.0), spacing=0.1)
# the iteration sweep's 5-iteration bar swings back to x = -0.45 m: a wider view than BAR_CAMERA, so
# that it stays in its (narrower) third of the frame
SWEEP3_CAMERA = Camera(eye=(0.05, -2.9, -0.25), target=(0.05, 0.0, -0.25), fov_degrees=34.0)
GHOST_NOTES = (
    "translucent red ghost: the converged implicit-Euler trajectory (same dt, Newton solved to convergence "
    "every step)",
    "off the ghost: the largest distance of a vertex from that trajectory, the error built up over all steps",
    "relative error = |x - x*| / |x* - x_n| of this step alone (x* = Newton from the same state): large when "
    "the step is small",
)


# the short bar from the front and a little above, filling the frame's width
CLOSE_BAR_CAMERA = Camera(eye=(0.25, -0.8, 0.25), target=(0.25, 0.0, -0.02), fov_degrees=35.0)
# Jacobi at 1e5 Pa: stiff enough that all-at-once solves overshoot, soft enough to stay on screen
JACOBI_E = 1e5
PROBE_MOVED = 1e-12     # m: a probe vertex that has moved more than this has "moved at all" (chapter 5)
# two iterations of the 20x4x4 bar's colours, plus the frame before the first colour
SWEEP_BY_COLOUR_FRAMES = 2 * 8 + 1


def _bar(label, youngs_modulus, iterations=20, mesh=SHORT_BAR, ghost=True, sweep=Sweep.GAUSS_SEIDEL):
    return Panel(label=label, mesh=mesh, material=_material(youngs_modulus), iterations=iterations,
                 fixed=PINNED_LEFT, newton_ghost=ghost, show_wave_cells=True, sweep=sweep)


SCENES = {scene.name: scene for scene in [
    Scene(
        name="stiffness_sweep",
        title="Same VBD solver, 20 iterations per step, dt = 1/60 s: soft vs stiff cantilever",
        description="Cantilever bars (0.5 m, 20x4x4 cells) at E = 1e4 Pa and 1e6 Pa, dt = 1/60, 20 iterations "
                    "each. The red ghost follows the converged implicit-Euler trajectory: the soft bar "
                    "and its ghost coincide, while the stiff bar cannot propagate its stiffness along the "
                    "bar in 20 iterations and sags far below its stiff ghost, like a much softer material. "
                    "The soft bar stretches to almost twice its length under its own weight: that is "
                    "physics (1e4 Pa is very soft for a 0.5 m bar), and its converged ghost does the same.",
        panels=(_bar("E = 1e4 Pa (soft)", 1e4), _bar("E = 1e6 Pa (stiff)", 1e6)),
        camera=BAR_CAMERA, grid=BACK_WALL, frames=36, fps=20,
        notes=GHOST_NOTES,
    ),
    Scene(
        name="resolution_sweep",
        title="Same stiffness (E = 1e6 Pa) and 20 iterations, coarse vs fine mesh",
        description="0.5 m bars meshed with 10x2x2 and 20x4x4 cells, 20 iterations each. Information moves "
                    "about one ring of elements per iteration, so the fine mesh needs more iterations for "
                    "the same accuracy.",
        panels=(_bar("coarse 10x2x2 cells", 1e6, mesh=BoxMesh(size=(0.5, 0.1, 0.1), cells=(10, 2, 2))),
                _bar("fine 20x4x4 cells", 1e6)),
        camera=BAR_CAMERA, grid=BACK_WALL, frames=48, fps=24,
        notes=GHOST_NOTES,
    ),
    Scene(
        name="iteration_sweep",
        title="E = 1e6 Pa with 5, 20 and 100 iterations per step",
        description="One stiff bar at three iteration budgets: more iterations let the stiffness "
                    "reach further along the bar and the result approaches its converged ghost. The "
                    "distance to the ghost ('off the ghost', relative to the bar's length) ranks the "
                    "budgets as expected; the per-step relative error need not, because it divides by the "
                    "size of the step itself, which is small whenever a bar turns around.",
        panels=(_bar("E = 1e6 Pa, small budget", 1e6, 5), _bar("E = 1e6 Pa, lecture budget", 1e6, 20),
                _bar("E = 1e6 Pa, large budget", 1e6, 100)),
        camera=SWEEP3_CAMERA, grid=BACK_WALL, frames=48, fps=24,
        notes=GHOST_NOTES,
    ),
    Scene(
        name="remedy",
        title="The stiff bar at the same wall time per step: plain VBD vs two-level VBD",
        description="The stiffness sweep's stiff bar (0.5 m, 20x4x4 cells, E = 1e6 Pa, pinned left, dt = 1/60 s) "
                    "twice. Right: the remedy of lecture notes chapter 7, two-level VBD "
                    "(Simulation(method='multilevel')): 5 cycles per step, each 2 VBD sweeps, a correction "
                    "on a coarse cage that carries the stiffness along the whole bar at once, and 2 more "
                    "sweeps. Left: plain VBD with as many iterations per step as fit in the same wall time, "
                    "measured when the scene starts. Both carry the converged ghost. Plain VBD moves "
                    "information one ring of elements per sweep and still sags far below its ghost; the "
                    "two-level bar follows it.",
        panels=(Panel(label="plain VBD, iterations fitted to the two-level step's time", material=_material(1e6),
                      mesh=SHORT_BAR,
                      iterations=20, fixed=PINNED_LEFT, newton_ghost=True, same_wall_time_as=1,
                      show_step_time=True),
                Panel(label="remedy: two-level VBD (method='multilevel')", material=_material(1e6),
                      mesh=SHORT_BAR, iterations=20, fixed=PINNED_LEFT, newton_ghost=True,
                      method=solver.Method.MULTILEVEL, show_step_time=True)),
        camera=BAR_CAMERA, grid=BACK_WALL, frames=36, fps=20,
        notes=GHOST_NOTES + ("ms/step: median time of the panel's own steps so far (ghost excluded); plain VBD's "
                             "iterations are fitted at the start",),
    ),
    Scene(
        name="propagation",
        title="One time step, iteration by iteration",
        description="A stiff bar (E = 1e6 Pa, no gravity) pinned on the left; its right end is moved "
                    "down 5 cm at the start of the step. Each frame is one more VBD iteration; "
                    "vertices are coloured by how far they have moved, so the front visibly travels "
                    "about one ring of elements per iteration.",
        panels=(Panel(label="E = 1e6 Pa, right end moved 5 cm", material=_material(1e6),
                      iterations=1, fixed=PINNED_LEFT, kinematic=(EndFace(0, Side.HIGH),), motion=Shift(),
                      initial_guess=solver.InitialGuess.PREVIOUS, newton_ghost=True),),
        camera=Camera(eye=(0.5, -1.9, 0.25), target=(0.5, 0.0, 0.0), fov_degrees=35.0),
        grid=BACK_WALL, gravity=(0.0, 0.0, 0.0), frames=41, fps=5,
        color_by=ColorBy.DISPLACEMENT, color_range=(1e-6, 5e-2), advance=Advance.ITERATIONS,
        notes=("colour: distance moved in this step (log scale); red ghost: converged Newton step",),
    ),
    Scene(
        name="jacobi_vs_colouring",
        title="Without colours: Jacobi (every vertex at once) vs coloured Gauss-Seidel, 20 iterations per step",
        description="The stiffness sweep's bar (0.5 m, 20x4x4 cells, pinned left, dt = 1/60 s) at E = 1e5 Pa twice. "
                    "Right: VBD's coloured Gauss-Seidel, colour after colour, each vertex solving with the "
                    "neighbours already moved in this sweep. Left: Jacobi, every vertex solving at once "
                    "against the positions of the previous iteration. Each vertex's solve assumes its "
                    "neighbours stay put; when all of them move at once, the moves add up and overshoot, "
                    "so Jacobi falls behind the ghost or runs away where the colouring converges.",
        panels=(_bar("Jacobi: all vertices at once", JACOBI_E, sweep=Sweep.JACOBI),
                _bar("coloured Gauss-Seidel (VBD)", JACOBI_E)),
        camera=BAR_CAMERA, grid=BACK_WALL, frames=36, fps=20,
        notes=GHOST_NOTES,
    ),
    Scene(
        name="probe",
        title="How many iterations until the far end feels it? One step, iteration by iteration",
        description="A stiff bar (0.5 m, 20x4x4 cells, E = 1e6 Pa, no gravity) whose left end is moved down 5 cm "
                    "at the start of one time step, initial guess x_n. The probe, the free right end's vertex "
                    "nearest the camera, is highlighted; its label says at which iteration it first moved at all "
                    f"(by more than {PROBE_MOVED:g} m, the threshold of lecture notes chapter 5): about one ring "
                    "of elements per iteration.",
        panels=(Panel(label="E = 1e6 Pa, left end moved 5 cm; probe at the free end", material=_material(1e6),
                      mesh=SHORT_BAR, iterations=1, kinematic=(EndFace(0, Side.LOW),), motion=Shift(),
                      initial_guess=solver.InitialGuess.PREVIOUS, probe=(EndFace(0, Side.HIGH),),
                      show_wave_cells=True),),
        camera=CLOSE_BAR_CAMERA, grid=BACK_WALL, gravity=(0.0, 0.0, 0.0), frames=31, fps=5,
        color_by=ColorBy.DISPLACEMENT, color_range=(1e-6, 5e-2), advance=Advance.ITERATIONS,
        notes=("colour: distance moved in this step (log scale); magenta: the probe vertex",),
    ),
    Scene(
        name="sweep_by_colour",
        title="One VBD iteration, colour by colour",
        description="A stiff bar (0.5 m, 20x4x4 cells, E = 1e6 Pa, no gravity) pinned on the left, its right end "
                    "moved down 5 cm. Each frame solves one more colour set: all its vertices at once, each "
                    "with its neighbours held where the earlier colours left them. Solved colours are shown "
                    "in their colour, the rest in grey; two iterations in all.",
        panels=(Panel(label="E = 1e6 Pa, right end moved 5 cm", material=_material(1e6), mesh=SHORT_BAR,
                      iterations=1, fixed=PINNED_LEFT, kinematic=(EndFace(0, Side.HIGH),), motion=Shift(),
                      initial_guess=solver.InitialGuess.PREVIOUS, show_wave_cells=True),),
        camera=CLOSE_BAR_CAMERA,
        grid=BACK_WALL, gravity=(0.0, 0.0, 0.0), frames=SWEEP_BY_COLOUR_FRAMES, fps=2,
        color_by=ColorBy.COLOR_SETS, advance=Advance.COLOURS,
    ),
    Scene(
        name="colouring",
        title="Graph colouring: vertices of one colour are solved in parallel",
        description="Vertices that share a tet get different colours; each colour set is one parallel "
                    "sweep of a VBD iteration. Pinned vertices (grey) are never solved.",
        panels=(Panel(label="bar 40x4x4 cells", material=_material(1e6), fixed=PINNED_LEFT),),
        camera=Camera(eye=(0.3, -0.9, 0.45), target=(0.5, 0.0, 0.0), fov_degrees=40.0),
        grid=BACK_WALL, gravity=(0.0, 0.0, 0.0), frames=1, fps=1, color_by=ColorBy.COLOR_SETS,
        advance=Advance.REST,
    ),
    Scene(
        name="drop",
        title="A soft ball dropped on the ground (penalty contact)",
        description="A voxelised sphere (radius 0.1 m, E = 1e5 Pa) falls from 0.5 m onto a penalty ground plane "
                    "and bounces.",
        panels=(Panel(label="E = 1e5 Pa, ground friction 0.5", material=_material(1e5),
                      mesh=AssetMesh("assets/sphere.obj", resolution=12, offset=(0.0, 0.0, 0.5)),
                      iterations=40, show_drift=True),),
        camera=Camera(eye=(0.0, -1.25, 0.55), target=(0.0, 0.0, 0.3), fov_degrees=38.0),
        ground=solver.Ground(height=0.0, stiffness=1e5, friction=0.5), grid=GridPlane(), frames=90,
        notes=("unconverged steps do not conserve momentum; the translation correction keeps the drift near "
               "1.5 cm (31 without)",),
    ),
    Scene(
        name="twist",
        title="A bar twisted by turning its ends (scripted vertices)",
        description="Both end faces of a bar (E = 1e5 Pa, no gravity) are rotated in opposite "
                    "directions about its axis at 90 degrees per second each.",
        panels=(Panel(label="E = 1e5 Pa, ends turned 90 degrees/s each", material=_material(1e5),
                      iterations=50, kinematic=(EndFace(0, Side.LOW), EndFace(0, Side.HIGH)), motion=Twist()),),
        camera=Camera(eye=(0.2, -1.6, 0.6), target=(0.5, 0.0, 0.05), fov_degrees=40.0),
        grid=BACK_WALL, gravity=(0.0, 0.0, 0.0), frames=120,
    ),
]}


# contact between bodies (lecture notes chapter 8): balls of radius 0.1 m
BALL_R = 0.1
BALL = BallMesh(radius=BALL_R, cells=4)
PILE_W, PILE_T, PILE_H, PILE_GAP = 0.45, 0.03, 0.35, 0.006   # m: box inside width, wall thickness, wall height,
#                                                           the walls' clearance off the floor (bodies may not touch)
PILE_WALLS = (BoxMesh(size=(PILE_W + 2 * PILE_T, PILE_W + 2 * PILE_T, PILE_T), cells=(3, 3, 1),
                      origin=(-PILE_T, -PILE_T, -PILE_T)),
              BoxMesh(size=(PILE_T, PILE_W + 2 * PILE_T, PILE_H), cells=(1, 3, 2), origin=(-PILE_T, -PILE_T, PILE_GAP)),
              BoxMesh(size=(PILE_T, PILE_W + 2 * PILE_T, PILE_H), cells=(1, 3, 2), origin=(PILE_W, -PILE_T, PILE_GAP)),
              BoxMesh(size=(PILE_W - 2 * PILE_GAP, PILE_T, PILE_H), cells=(3, 1, 2),
                      origin=(PILE_GAP, -PILE_T, PILE_GAP)),
              BoxMesh(size=(PILE_W - 2 * PILE_GAP, PILE_T, PILE_H), cells=(3, 1, 2), origin=(PILE_GAP, PILE_W, PILE_GAP)))
# two layers of 2 x 2 balls, the upper one shifted 1 cm in x so that it does not land exactly on top
PILE_BALLS = tuple((0.1125 + 0.225 * i + 0.01 * k, 0.1125 + 0.225 * j, 0.11 + 0.23 * k)
                   for k in range(2) for i in range(2) for j in range(2))
PILE_CONTACT = solver.Contact(stiffness=1e4, radius=0.005, friction=0.3)
HEAD_ON_CONTACT = solver.Contact(stiffness=1e3, radius=0.01)
COIL_CONTACT = solver.Contact(stiffness=1e4, radius=0.005)

SCENES.update({scene.name: scene for scene in [
    Scene(
        name="pile",
        title="Eight soft balls dropped into an open box (contact, friction 0.3)",
        description="Eight balls (radius 0.1 m, 384 tets each, E = 1e5 Pa) in two layers of 2 x 2 fall into an open "
                    "box of five fixed slabs. Contact between bodies is OGC's two-stage barrier (radius 5 mm, "
                    "k = 1e4 N/m, friction 0.3); between refreshes of the bounds each vertex moves at most 0.45 of "
                    "its distance to its closest pair, so no ball crosses another or a wall.",
        panels=(Panel(label="8 balls, E = 1e5 Pa, contact friction 0.3", material=_material(1e5),
                      mesh=Bodies(PILE_WALLS + (BALL,) * 8, ((0.0, 0.0, 0.0),) * 5 + PILE_BALLS),
                      iterations=20, fixed=(Outside(upper=(PILE_W, PILE_W, np.inf)),), contact=PILE_CONTACT),),
        camera=Camera(eye=(0.225, -0.55, 1.35), target=(0.225, 0.225, 0.12), fov_degrees=40.0),
        frames=90,
        notes=("contacts: pairs closer than the barrier's radius; closest gap: the least pair distance",),
    ),
    Scene(
        name="head_on",
        title="Two soft balls meet head-on at 1 m/s each (no gravity, no friction)",
        description="Two balls (radius 0.1 m, 384 tets each, E = 1e5 Pa) 10 cm apart move towards each other at 1 m/s "
                    "each, without gravity or friction, and rebound off the contact barrier (radius 1 cm, "
                    "k = 1e3 N/m). The total momentum stays near zero. The ghost is the converged trajectory "
                    "(Newton with contact, method='newton'); the error compares each VBD step with the "
                    "converged one.",
        panels=(Panel(label="two balls at +-1 m/s, E = 1e5 Pa", material=_material(1e5),
                      mesh=Bodies((BALL, BALL), ((0.0, 0.0, 0.0), (2 * BALL_R + 0.1, 0.0, 0.0))),
                      iterations=20, contact=HEAD_ON_CONTACT, velocity=Approach(1.0), show_momentum=True,
                      newton_ghost=True),),
        camera=Camera(eye=(0.15, -1.3, 0.3), target=(0.15, 0.0, 0.0), fov_degrees=38.0),
        gravity=(0.0, 0.0, 0.0), dt=1.0 / 240.0, frames=90,
        notes=("ghost: the converged trajectory, Newton with contact started within the contact bounds every step",),
    ),
    Scene(
        name="self_contact",
        title="The twist bar turned until it coils onto itself (self contact)",
        description="The twist scene's bar (1 m, 40x4x4 cells, E = 1e5 Pa, no gravity), its ends turned at 360 "
                    "degrees per second each and pushed towards each other at 0.1 m/s each: it buckles and coils, "
                    "and self contact (radius 5 mm, k = 1e4 N/m) keeps its coils from passing through each other.",
        panels=(Panel(label="E = 1e5 Pa, ends turned 360 degrees/s, self contact", material=_material(1e5),
                      iterations=50, kinematic=(EndFace(0, Side.LOW), EndFace(0, Side.HIGH)),
                      motion=Coil(degrees_per_second=720.0, approach=0.1), contact=COIL_CONTACT),),
        camera=Camera(eye=(0.2, -1.6, 0.6), target=(0.5, 0.0, 0.05), fov_degrees=40.0),
        grid=BACK_WALL, gravity=(0.0, 0.0, 0.0), frames=150,
    ),
]})


@dataclass(frozen=True)
class Highest:
    """The highest ``fraction`` of the vertices along ``axis`` (at least one): where a body hangs from."""

    fraction: float = 0.05
    axis: int = 2

    def select(self, vertices):
        mask = np.zeros(len(vertices), bool)
        count = max(1, int(round(self.fraction * len(vertices))))
        mask[np.argsort(-vertices[:, self.axis], kind="stable")[:count]] = True
        return mask


SLIVER_BUNNY = AssetMesh("assets/bunny_slivers.vtu", offset=(0.0, 0.0, 0.3), expect_slivers=True)


def _real_shapes():
    """Meshes nobody here drew: the Stanford Bunny and Keenan Crane's Spot (assets/README.md), made
    into tets by fTetWild, hung and dropped; and a bunny meshed without shape optimisation, whose
    slivers an unconverged solve turns inside out."""
    hang = (Highest(0.05),)
    return Scene(
        name="real_shapes",
        title="Real shapes: a bunny, the same bunny full of slivers with and without keep_orientation, a dropped cow",
        description="Public surfaces tetrahedralised by assets/make_assets.py (fTetWild), 0.2 m long, "
                    "50 VBD iterations per step, dt = 1/60 s. Left: the Stanford Bunny (E = 1e5 Pa) hangs "
                    "from its highest 5 % of vertices. Next: the same bunny meshed without shape "
                    "optimisation (4,166 of 10,484 tets are slivers), hung the same way: plain VBD turns "
                    "slivers inside out and never recovers (about 175 tets after 30 steps, where converged "
                    "Newton has 1); with keep_orientation (an inversion-free guess and step-limited vertex "
                    "solves) none inverts, but a sliver cannot turn one vertex at a time, so that bunny hangs "
                    "stiffer than the well-shaped one: remeshing is the real cure. Right: Spot the cow "
                    "(E = 1e6 Pa) falls 5 cm onto the ground; 50 iterations leave it much softer than its E, "
                    "so its head sinks and it tips over.",
        panels=(
            Panel(label="bunny (5,108 tets), hung", material=_material(1e5),
                  mesh=AssetMesh("assets/bunny.vtu", offset=(0.0, 0.0, 0.3)), iterations=50, fixed=hang,
                  show_inverted=True),
            Panel(label="bunny, 4,166 slivers, hung: plain VBD", material=_material(1e5),
                  mesh=SLIVER_BUNNY, iterations=50, fixed=hang,
                  show_inverted=True),
            Panel(label="bunny, 4,166 slivers, hung: keep_orientation", material=_material(1e5),
                  mesh=SLIVER_BUNNY, iterations=50, fixed=hang,
                  keep_orientation=True, show_inverted=True),
            Panel(label="Spot (3,751 tets, E = 1e6 Pa), dropped", material=_material(1e6),
                  mesh=AssetMesh("assets/spot.vtu", offset=(0.0, 0.0, 0.05)), iterations=50, show_inverted=True),
        ),
        camera=Camera(eye=(0.0, -1.6, 0.5), target=(0.0, 0.0, 0.16), fov_degrees=36.0),
        ground=solver.Ground(height=0.0, stiffness=1e5, friction=0.5), grid=GridPlane(), frames=90,
        notes=("assets: Stanford Bunny (Stanford Computer Graphics Laboratory), Spot (Keenan Crane, CC0)",),
    )


SCENES["real_shapes"] = _real_shapes()

DEFAULT_SCENE = "stiffness_sweep"


def get(name):
    """The scene called ``name``; a DemoError naming the known scenes otherwise."""
    try:
        return SCENES[name]
    except KeyError:
        raise DemoError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}") from None
