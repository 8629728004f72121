"""Translation lag: what the per-body translation correction buys where a fixed body shares the mesh.

Unconverged VBD moves a free body too slowly (its residuals do not sum to zero); the translation
correction (`solver/vbd/translation.py`) translates each body without fixed vertices by its own d_b.
Two measurements, each with the correction on and off (`translation_correction`), float64 on the CPU:
  * incline: a soft cube on a fixed slab under gravity tilted by 30 degrees, contact friction mu = 0.3
    and mu = 0 (`tests/test_contact_sim.py`'s set-up), 20, 30 and 60 VBD iterations per step: the cube's
    mean acceleration over steps 15 to 45 as a fraction of g (sin - mu cos) (1: no lag);
  * pile: the piles of `benchmarks.contact` (k^3 soft cubes dropped into a fixed open box, friction 0.3,
    20 iterations): the cubes' mean vertex speed in m/s after settling (0 at rest).

    python -m benchmarks.translation_lag --out benchmarks/results/translation_lag
    python -m benchmarks.translation_lag --quick --out /tmp/translation_lag
"""
import numpy as np

from benchmarks.common import (init_taichi, output_folder, parser, positive, print_written, progress, provenance,
                               table, write_csv)

OUTPUTS = ("translation_lag.csv", "summary.md")
COLUMNS = ["scene", "mu", "bodies", "iterations", "correction", "acceleration_fraction", "mean_speed"]
THETA = np.radians(30.0)
SOFT = dict(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)


def measure_incline(solver, mu, iterations, correction, steps):
    """The cube's mean acceleration along the slope over steps steps // 3 .. steps, over g (sin - mu cos)."""
    slab = solver.box_mesh(size=(1.2, 0.3, 0.05), cells=(12, 3, 1), origin=(-0.1, -0.1, -0.05))
    cube = solver.box_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1), origin=(0.0, 0.0, 0.0045))
    mesh = solver.merge_meshes([slab, cube])
    n = slab.n_vertices
    gravity = 9.81 * np.array([np.sin(THETA), 0.0, -np.cos(THETA)])
    contact = solver.Contact(stiffness=1e4, radius=0.005, friction=mu)
    sim = solver.Simulation(mesh, solver.Material(**SOFT), dt=1 / 60, gravity=gravity, fixed=np.arange(n),
                            iterations=iterations, contact=contact, translation_correction=correction)
    m = sim.masses[n:]
    v = []
    for _ in range(steps):
        sim.step()
        v.append(m @ sim.velocities[n:, 0] / m.sum())
    first = steps // 3
    a = (v[-1] - v[first - 1]) / ((steps - first) * sim.dt)
    return dict(scene="incline", mu=mu, bodies=1, iterations=iterations, correction=correction,
                acceleration_fraction=a / (9.81 * (np.sin(THETA) - mu * np.cos(THETA))))


def measure_pile(solver, k, correction, settle):
    """Mean vertex speed of the cubes after `settle` steps."""
    from benchmarks.contact import pile_scene

    mesh, n_walls = pile_scene(solver, k, apart=False)
    contact = solver.Contact(stiffness=1e4, radius=0.005, friction=0.3)
    sim = solver.Simulation(mesh, solver.Material(**SOFT), dt=1 / 60, fixed=np.arange(n_walls), iterations=20,
                            contact=contact, translation_correction=correction)
    sim.step(settle)
    mean_speed = float(np.linalg.norm(sim.velocities[n_walls:], axis=1).mean())
    return dict(scene="pile", mu=0.3, bodies=k ** 3, iterations=20, correction=correction,
                mean_speed=mean_speed)


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/translation_lag",
               quick="20 iterations only, 6 incline steps (not 45) and the pile of one cube")
    p.add_argument("--settle", type=positive(int), default=90, quick=3,
                   help="steps (1/60 s) each pile falls before measuring")
    args = p.parse_args(argv)
    out = output_folder(args, OUTPUTS)
    iterations = (20,) if args.quick else (20, 30, 60)
    piles = (1,) if args.quick else (1, 2, 3)
    incline_steps = 6 if args.quick else 45
    settle = args.settle
    init_taichi()
    import solver

    cases = [("incline", mu, it, c) for mu in (0.3, 0.0) for it in iterations for c in (True, False)]
    cases += [("pile", k, None, c) for k in piles for c in (True, False)]
    rows = []
    for scene, a, b, correction in progress(cases, desc="cases", disable=args.no_progress):
        if scene == "incline":
            rows.append(measure_incline(solver, a, b, correction, incline_steps))
        else:
            rows.append(measure_pile(solver, a, correction, settle))
    text = table(rows, COLUMNS, title="Translation correction per body (float64, CPU)")
    print(text)
    write_csv(f"{out}/translation_lag.csv", rows, COLUMNS)
    with open(f"{out}/summary.md", "w") as fh:
        fh.write(f"{provenance()}\n\nacceleration_fraction: the sliding cube's acceleration over g (sin - mu cos), "
                 f"1 for no lag; mean_speed: the settled pile's mean vertex speed in m/s.\n\n"
                 f"{text}\n")
    print_written(args, OUTPUTS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
