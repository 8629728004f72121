"""Contact cost: step time against active contacts, detection against one sweep, the sweep with and without contact.

Three measurements, all float64 on the CPU, ratios taken within one run (issue 17's performance targets):
  * piles of 1, 8, 27 and 64 soft balls (the sphere asset voxelised at resolution 3, 114 tets each: the
    bodies issue 17 names; and as "fine ball pile" at --fine-resolution, 816 tets each at 6, whose
    surface is a smaller share of the ball) dropped into a fixed open box of five slabs, friction 0.3: median step time, full
    detections and refreshes of the bounds per step and active contacts (pairs closer than the radius)
    once settled: stepped until the mean vertex speed is under 1 mm/s, checked every second, at most
    --settle steps (settle_s: how long it took, in whole seconds; at the cap the pile did not settle, as
    under --quick; mean_speed: that speed in m/s after the timed steps; a pile still moving detects about
    once in ten steps, which would be timed as well), against the same bodies set apart above the
    box with no gravity (target: at most 2x), the two scenes stepped in turn (step_ratio: the median of the
    ratios of the steps taken in turn); and the same piles of cubes as wide (2 x 2 x 2 cells, 48 tets
    each), bodies that are nearly all surface;
  * one detection (`ContactDetector.detect`) against one elastic sweep (`run_iterations(1)` without
    contact) on the same settled pile and on the large meshes below, the fastest of 3 interleaved timings
    of each (target: at most 1x), with the pairs it returns (every pair within query_radius: each is one
    exact distance) and its time per pair, against the time per pair at which it would cost one sweep.
    Set apart, the bodies are left out of the search (far from the others, moved rigidly); touching
    (1.5 mm gaps, inside the radius) they are all searched;
  * ns per tet per VBD iteration of 8 bodies of 3,072 tets (24,576 tets) set apart, no gravity, with
    contact on (nothing within query_radius) and with contact=None, the fastest of 3 interleaved timings
    of each (target: at most 1.25x).

    python -m benchmarks.contact --out benchmarks/results/contact
    python -m benchmarks.contact --quick --out /tmp/contact
"""
import time
import warnings
from pathlib import Path

import numpy as np

from benchmarks.common import (init_taichi, output_folder, parser, positive, print_written, progress, provenance,
                               seconds_per_call, sync, table, voxel_resolution, write_csv)

OUTPUTS = ("contact.csv", "contact.png", "summary.md")
COLUMNS = ["measurement", "bodies", "body_tets", "tets", "contacts", "settle_s", "mean_speed", "detections_per_step",
           "refreshes_per_step", "step_ms", "apart_step_ms", "step_ratio", "pairs", "detect_ms", "detect_ns_per_pair",
           "sweep_ms", "break_even_ns_per_pair", "detect_per_sweep", "ns_per_tet_iter_none", "ns_per_tet_iter_contact",
           "contact_per_none"]
SIZE, PITCH, GAP, WALL = 0.08, 0.14, 0.006, 0.02      # m: cube edge, cube spacing, wall gap, wall thickness
ROUNDS = 3                                            # interleaved timings of the sweep with and without contact
SOFT = dict(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
SETTLE_CHECK, SETTLED = 60, 1e-3                       # steps between checks; m/s: a pile is settled below this
BALL_ASSET = Path(__file__).resolve().parent.parent / "assets" / "sphere.obj"
BALL_RESOLUTION, FINE_RESOLUTION = 3, 6                 # voxels across the ball asset: 114 and 816 tets a ball


def _walls(solver, k):
    """The five fixed slabs of an open box holding k x k cubes per layer, k + 1 layers high."""
    W, T, H = k * PITCH + 0.02, WALL, (k + 1) * 0.1
    n = 3 * k
    return [solver.box_mesh(size=(W + 2 * T, W + 2 * T, T), cells=(n, n, 1), origin=(-T, -T, -T)),
            solver.box_mesh(size=(T, W + 2 * T, H), cells=(1, n, k + 1), origin=(-T, -T, GAP)),
            solver.box_mesh(size=(T, W + 2 * T, H), cells=(1, n, k + 1), origin=(W, -T, GAP)),
            solver.box_mesh(size=(W - 2 * GAP, T, H), cells=(n, 1, k + 1), origin=(GAP, -T, GAP)),
            solver.box_mesh(size=(W - 2 * GAP, T, H), cells=(n, 1, k + 1), origin=(GAP, W, GAP))]


def _ball(solver, resolution):
    """The sphere asset voxelised at `resolution` (3: 114 tets, 56 vertices; 6: 816 tets, 251 vertices) and
    scaled to a ball of diameter SIZE whose box's corner is at the origin, as a cube's."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", solver.MeshQualityWarning)
        ball = solver.load_mesh(str(BALL_ASSET), resolution=resolution)
    x = ball.vertices - ball.vertices.min(axis=0)
    return solver.TetMesh(x * (SIZE / np.ptp(x, axis=0).max()), ball.tets)


def pile_scene(solver, k, apart, balls=0):
    """k^3 cubes (or, where balls is a voxel resolution, balls of the same width) in layers of k x k inside
    the box (apart=False) or spread out above it, 2 pitches apart (apart=True); returns (mesh, number of
    wall vertices)."""
    walls = _walls(solver, k)
    top = (k + 1) * 0.1 + 0.1
    if apart:
        origins = [(0.04 + 2 * PITCH * i, 0.04 + 2 * PITCH * j, top + 2 * PITCH * layer)
                   for layer in range(k) for i in range(k) for j in range(k)]
    else:
        origins = [(0.04 + PITCH * i + 0.01 * (layer % 2), 0.04 + PITCH * j, 0.01 + 0.1 * layer)
                   for layer in range(k) for i in range(k) for j in range(k)]
    if balls:
        ball = _ball(solver, balls)
        bodies = [solver.TetMesh(ball.vertices + np.asarray(o), ball.tets) for o in origins]
    else:
        bodies = [solver.box_mesh(size=(SIZE,) * 3, cells=(2, 2, 2), origin=o) for o in origins]
    return solver.merge_meshes(walls + bodies), sum(w.n_vertices for w in walls)


def _steps_in_turn(sims, steps):
    """Step each simulation in turn, `steps` times: per simulation the median seconds of a step and the mean
    numbers of full detections and of refreshes per step (the contact stage's counters: each step starts
    with a refresh at its clamped guess, and one at x_n first where the guess needs clamping; every
    iteration after a bound hit adds one;
    a refresh turns into a full detection when the positions moved too far); and the median over the
    rounds of the first simulation's step over the second's. Taken in turn, a drift of the machine's
    speed moves both alike."""
    stages = [sim._contact_stage for sim in sims]
    counters = [(stage.detections, stage.refreshes) for stage in stages]
    samples = np.zeros((steps, len(sims)))
    for row in samples:
        for j, sim in enumerate(sims):
            t = time.perf_counter()
            sim.step()
            sync()
            row[j] = time.perf_counter() - t
    per_sim = [(float(np.median(samples[:, j])), (stage.detections - d) / steps, (stage.refreshes - r) / steps)
               for j, (stage, (d, r)) in enumerate(zip(stages, counters))]
    return per_sim, float(np.median(samples[:, 0] / samples[:, 1]))


def _detect_and_sweep(solver, sim, mesh, fixed, min_seconds):
    """Seconds of one detection at the simulation's positions and of one sweep without contact there, and
    the pairs that detection returns (every pair within query_radius, each one exact distance)."""
    from solver.physics.contact_detection import ContactDetector
    from solver.vbd.layout import X

    detector = ContactDetector(mesh, sim.free_mask, sim.contact, sim.dtype)
    plain = solver.Simulation(mesh, solver.Material(**SOFT), dt=sim.dt, fixed=fixed, iterations=1)
    plain.set_positions(sim.positions)
    plain.begin_step()
    detect_s, sweep_s = [], []
    for _ in range(ROUNDS):                  # interleaved, the fastest round of each: the machine is shared
        detect_s.append(seconds_per_call(lambda k: [detector.detect(sim.state, X) for _ in range(k)], min_seconds)[0])
        sweep_s.append(seconds_per_call(plain.run_iterations, min_seconds)[0])
    return min(detect_s), min(sweep_s), detector.n_pairs


def measure_pile(solver, k, settle, timed, min_seconds, measurement, balls=0):
    """One pile row: k^3 bodies (`pile_scene`) settled, then stepped in turn with the same bodies set apart."""
    contact = solver.Contact(stiffness=1e4, radius=0.005, friction=0.3)
    mat = solver.Material(**SOFT)
    mesh, n_walls = pile_scene(solver, k, apart=False, balls=balls)
    body_tets = (mesh.n_tets - sum(w.n_tets for w in _walls(solver, k))) // k ** 3
    fixed = np.arange(n_walls)
    sim = solver.Simulation(mesh, mat, dt=1 / 60, fixed=fixed, iterations=20, contact=contact)
    settled = 0
    while settled < settle:         # until the bodies' mean vertex speed is under SETTLED, at most `settle` steps
        steps = min(SETTLE_CHECK, settle - settled)
        sim.step(steps)
        settled += steps
        if np.linalg.norm(sim.velocities[n_walls:], axis=1).mean() < SETTLED:
            break
    far, _ = pile_scene(solver, k, apart=True, balls=balls)
    apart = solver.Simulation(far, mat, dt=1 / 60, fixed=fixed, gravity=(0, 0, 0), iterations=20, contact=contact)
    apart.step()
    ((step_s, detections, refreshes), (apart_s, _, _)), ratio = _steps_in_turn((sim, apart), timed)
    contacts = sim.contact_count()
    mean_speed = float(np.linalg.norm(sim.velocities[n_walls:], axis=1).mean())
    detect_s, sweep_s, pairs = _detect_and_sweep(solver, sim, mesh, fixed, min_seconds)
    return dict(measurement=measurement, bodies=k ** 3, body_tets=body_tets, tets=mesh.n_tets, contacts=contacts,
                settle_s=settled * sim.dt, mean_speed=mean_speed, detections_per_step=detections,
                refreshes_per_step=refreshes, step_ms=step_s * 1e3, apart_step_ms=apart_s * 1e3, step_ratio=ratio,
                **_detection_columns(detect_s, sweep_s, pairs))


def _detection_columns(detect_s, sweep_s, pairs):
    """The detection columns of a row; where the detection found pairs, its time per pair and the time per pair
    at which it would cost one sweep (break_even_ns_per_pair: the sweep's time over the pairs)."""
    per_pair = {}
    if pairs:
        per_pair = dict(detect_ns_per_pair=detect_s * 1e9 / pairs, break_even_ns_per_pair=sweep_s * 1e9 / pairs)
    return dict(pairs=pairs, detect_ms=detect_s * 1e3, **per_pair, sweep_ms=sweep_s * 1e3,
                detect_per_sweep=detect_s / sweep_s)


def measure_apart(solver, cells, min_seconds):
    """8 bodies of cells^3 x 6 tets, 2 body widths apart, no gravity: the sweep with and without contact."""
    side = 0.1
    bodies = [solver.box_mesh(size=(side,) * 3, cells=(cells,) * 3, origin=(3 * side * i, 3 * side * j, 3 * side * m))
              for i in range(2) for j in range(2) for m in range(2)]
    mesh = solver.merge_meshes(bodies)
    mat = solver.Material(**SOFT)
    sims = {}
    for name, contact in (("none", None), ("contact", solver.Contact(stiffness=1e4, radius=0.002))):
        sims[name] = solver.Simulation(mesh, mat, dt=1 / 60, gravity=(0, 0, 0), iterations=1, contact=contact)
        sims[name].begin_step()
    seconds = {name: [] for name in sims}
    for _ in range(ROUNDS):                  # interleaved, the fastest round of each: the machine is shared
        for name, sim in sims.items():
            seconds[name].append(seconds_per_call(sim.run_iterations, min_seconds)[0])
    seconds = {name: min(v) for name, v in seconds.items()}
    contacts = sims["contact"].contact_count()
    ns = {k: v / mesh.n_tets * 1e9 for k, v in seconds.items()}
    return dict(measurement="apart, no gravity", bodies=len(bodies), tets=mesh.n_tets, contacts=contacts,
                **_detection_columns(*_detect_and_sweep(solver, sims["contact"], mesh, None, min_seconds)),
                ns_per_tet_iter_none=ns["none"], ns_per_tet_iter_contact=ns["contact"],
                contact_per_none=ns["contact"] / ns["none"])


def measure_touching(solver, cells, min_seconds):
    """The 8 bodies of `measure_apart` in a 2 x 2 x 2 block with 1.5 mm gaps (under the radius): one
    detection, where every body is searched, against one sweep."""
    side, gap = 0.1, 0.0015
    bodies = [solver.box_mesh(size=(side,) * 3, cells=(cells,) * 3,
                              origin=((side + gap) * i, (side + gap) * j, (side + gap) * m))
              for i in range(2) for j in range(2) for m in range(2)]
    mesh = solver.merge_meshes(bodies)
    sim = solver.Simulation(mesh, solver.Material(**SOFT), dt=1 / 60, gravity=(0, 0, 0), iterations=1,
                            contact=solver.Contact(stiffness=1e4, radius=0.002))
    return dict(measurement="touching, no gravity", bodies=len(bodies), tets=mesh.n_tets, contacts=sim.contact_count(),
                **_detection_columns(*_detect_and_sweep(solver, sim, mesh, None, min_seconds)))


def plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, ratio, b) = plt.subplots(1, 3, figsize=(16, 4.5))
    shapes = (("balls", ("^-", "v--"), "C0"), ("fine balls", ("D-", "d--"), "C2"), ("cubes", ("o-", "s--"), "C1"))
    for shape, marks, colour in shapes:
        piles = [r for r in rows if r["measurement"] == f"{shape[:-1]} pile"]
        if not piles:
            continue
        name = f"{shape} of {piles[0]['body_tets']} tets"
        a.plot([r["contacts"] for r in piles], [r["step_ms"] for r in piles], marks[0], color=colour,
               label=f"pile of {name}")
        a.plot([r["contacts"] for r in piles], [r["apart_step_ms"] for r in piles], marks[1], color=colour,
               label=f"same {shape} apart")
        for r in piles:
            a.annotate(f"{r['bodies']}", (r["contacts"], r["step_ms"]), fontsize=8)
        ratio.plot([r["bodies"] for r in piles], [r["step_ratio"] for r in piles], marks[0], color=colour, label=name)
    a.set_xlabel("active contacts (pairs closer than the radius)")
    a.set_ylabel("ms per step (20 iterations)")
    a.set_title("Step time against active contacts")
    a.legend(fontsize=7)
    ratio.axhline(2.0, color="k", lw=0.8, ls=":", label="target")
    ratio.set_xscale("log")
    bodies = sorted({r["bodies"] for r in rows if r["measurement"].endswith("pile")})
    ratio.set_xticks(bodies, [str(n) for n in bodies])
    ratio.minorticks_off()
    ratio.set_xlabel("bodies in the pile")
    ratio.set_ylabel("pile step / the same bodies set apart")
    ratio.set_title("A settled pile against its bodies apart")
    ratio.legend(fontsize=7)
    colours = {f"{shape[:-1]} pile": colour for shape, _, colour in shapes}
    labels = [f"{r['measurement']}, {r['tets']} tets" for r in rows]
    b.barh(labels, [r["detect_per_sweep"] for r in rows], color=[colours.get(r["measurement"], "C7") for r in rows])
    b.axvline(1.0, color="k", lw=0.8, ls=":", label="target")
    b.invert_yaxis()
    b.set_xlabel("one detection / one sweep without contact")
    b.set_title("Detection against one elastic sweep")
    b.tick_params(axis="y", labelsize=7)
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/contact", quick="piles of 1 and 8 bodies (not up to 64)")
    p.add_argument("--settle", type=positive(int), default=1440, quick=3,
                   help="most steps (1/60 s) each pile falls before timing; it stops sooner once the mean vertex "
                        "speed is under 1 mm/s")
    p.add_argument("--steps", type=positive(int), default=40, quick=2,
                   help="timed steps per pile and per set-apart scene")
    p.add_argument("--min-seconds", type=positive(float), default=0.5, quick=0.02, help="least time per timing")
    p.add_argument("--cells", type=positive(int), default=8, quick=2,
                   help="cells per side of each of the 8 set-apart bodies (6 tets per cell; 8: 24,576 tets)")
    p.add_argument("--fine-resolution", type=voxel_resolution, default=FINE_RESOLUTION, quick=4,
                   help="voxels across the ball asset for the fine ball piles (6: 816 tets a ball, 4: 192)")
    args = p.parse_args(argv)
    out = output_folder(args, OUTPUTS)
    piles = (1, 2) if args.quick else (1, 2, 3, 4)
    fine_piles = (1,) if args.quick else piles
    settle, steps, min_seconds, cells = args.settle, args.steps, args.min_seconds, args.cells
    init_taichi()
    import solver

    rows = []
    shapes = (("ball pile", BALL_RESOLUTION, piles), ("fine ball pile", args.fine_resolution, fine_piles),
              ("cube pile", 0, piles))
    for measurement, balls, ks in shapes:
        for k in progress(ks, desc=f"{measurement}s", disable=args.no_progress):
            rows.append(measure_pile(solver, k, settle, steps, min_seconds, measurement, balls=balls))
    rows.append(measure_apart(solver, cells, min_seconds))
    rows.append(measure_touching(solver, cells, min_seconds))
    text = table(rows, COLUMNS, title="Contact cost (float64, CPU; ratios within this run)")
    print(text)
    write_csv(f"{out}/contact.csv", rows, COLUMNS)
    plot(rows, f"{out}/contact.png")
    with open(f"{out}/summary.md", "w") as fh:
        fh.write(f"{provenance()}\n\nMilliseconds move with the machine's load (2 shared cores here); "
                 f"compare the ratios, not the milliseconds.\n\n{text}\n")
    print_written(args, OUTPUTS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
