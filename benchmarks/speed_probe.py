"""The solver timings of `benchmarks.before_after`, run inside the checkout being measured.

It imports nothing of `benchmarks` and only the public `solver` names that were there before the
regroup (`box_mesh`, `Material`, `Method`, `Simulation` with `set_positions`, `begin_step`,
`run_iterations`, `step`), so the same file times an older checkout; the contact step runs only where
the checkout has `solver.Contact` and `solver.merge_meshes` (issue 17). Started as

    python benchmarks/speed_probe.py '{"classroom": [40, 4, 4], "large": [40, 20, 20], "vbd": true,
                                       "global": true, "contact": true}'

with that checkout first on PYTHONPATH, it prints ``RESULT {json}`` as its last line: for each
measurement its value and a checksum of the positions it reached (sum of |x|), so that a driver can
tell that both checkouts did the same work.
"""
import json
import sys
import time

import numpy as np

import solver

E_PA = 1e6              # the stiff bar of the lecture's failure case
STRETCH = 1.5           # the bar starts stretched to 1.5x its length along x, then is released
REPEATS = 7             # timed calls per measurement; the median is reported
LARGE_REPEATS = 30      # the same for the ~96k-tet iteration, whose time jumps for seconds on a shared host
CUBE, DROP = 0.08, 0.01     # m: the edge of each cube of the contact step, and its gap above the slab
FALL_STEPS = 10             # steps before the contact step is timed: the cubes have landed on the slab


def stretched_bar(cells, **settings):
    """A Simulation of a bar of `cells` (nx, ny, nz) cells of 0.1 m, pinned at x = 0 and stretched."""
    mesh = solver.box_mesh(size=(cells[0] / 10, cells[1] / 10, cells[2] / 10), cells=tuple(cells))
    sim = solver.Simulation(mesh, solver.Material(E_PA, 0.3, 1000.0), dt=1 / 60,
                            fixed=mesh.vertices[:, 0] < 1e-9, **settings)
    sim.set_positions(mesh.vertices * np.array([STRETCH, 1.0, 1.0]))
    return sim


def checksum(sim) -> float:
    """Sum of |x| over the positions: equal in two checkouts that took the same iterates."""
    return float(np.abs(sim.positions).sum())


def median_seconds(run, repeats=REPEATS) -> float:
    """Median wall time of run() over `repeats` calls, after one untimed call (compiles, builds caches). The
    same as `benchmarks.newton_speed.median_seconds`, written again: this file runs inside checkouts whose
    `benchmarks` is another version, or has none."""
    run()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        samples.append(time.perf_counter() - start)
    return float(np.median(samples))


def iteration_time(cells, per_call, calls, repeats=REPEATS):
    """(seconds per VBD iteration, checksum, tets), timed `repeats` times over `calls` calls of `per_call`
    iterations each, within one step."""
    sim = stretched_bar(cells, iterations=per_call)
    sim.begin_step()

    def run():
        for _ in range(calls):
            sim.run_iterations(per_call)
    return median_seconds(run, repeats) / (per_call * calls), checksum(sim), sim.mesh.n_tets


def step_time(cells, method, iterations):
    """(seconds per step of `method`, checksum): the median of the steps after the first."""
    sim = stretched_bar(cells, iterations=iterations, method=method)
    seconds = median_seconds(sim.step)
    return seconds, checksum(sim)


def contact_step():
    """(seconds per step, checksum, tets): 8 cubes of 48 tets, 2 x 2 side by side in two layers, dropped onto
    a fixed slab with friction, timed after FALL_STEPS steps, once they rest on it and on each other."""
    slab = solver.box_mesh(size=(0.4, 0.4, 0.02), cells=(6, 6, 1), origin=(-0.02, -0.02, -0.02))
    cubes = [solver.box_mesh(size=(CUBE,) * 3, cells=(2, 2, 2),
                             origin=(0.1 * i + 0.01 * layer, 0.1 * j, DROP + (CUBE + DROP) * layer))
             for layer in range(2) for i in range(2) for j in range(2)]
    mesh = solver.merge_meshes([slab] + cubes)
    sim = solver.Simulation(mesh, solver.Material(1e5, 0.3, 1000.0), dt=1 / 60, fixed=np.arange(slab.n_vertices),
                            iterations=20, contact=solver.Contact(stiffness=1e4, radius=0.005, friction=0.3))
    sim.step(FALL_STEPS)
    return median_seconds(sim.step), checksum(sim), mesh.n_tets


def measure(sizes) -> dict:
    """{measurement: [value, unit, checksum]} for the sizes and parts in `sizes`: the bars' cells
    ("classroom", "large") and which parts to run ("vbd", "global", "contact"; a part left out is not run)."""
    results = {}
    tets = 6 * int(np.prod(sizes["classroom"]))
    if sizes.get("vbd"):
        for per_call, calls in ((50, 1), (1, 50)):
            seconds, total, _ = iteration_time(sizes["classroom"], per_call, calls)
            results[f"VBD iteration, {tets:,} tets ({per_call} per call)"] = [1e3 * seconds, "ms", total]
        seconds, total, large = iteration_time(sizes["large"], 10, 1, LARGE_REPEATS)
        results[f"ns per tet-iteration, {large:,} tets"] = [1e9 * seconds / large, "ns", total]
    if sizes.get("global"):
        for name, method, iterations in (("Newton step", solver.Method.NEWTON, 100),
                                         ("Newton-PCG step", solver.Method.PCG, 100),
                                         ("two-level step, 5 cycles", solver.Method.MULTILEVEL, 20)):
            seconds, total = step_time(sizes["classroom"], method, iterations)
            results[f"{name}, {tets:,} tets"] = [1e3 * seconds, "ms", total]
    if sizes.get("contact") and hasattr(solver, "Contact") and hasattr(solver, "merge_meshes"):
        seconds, total, n = contact_step()
        results[f"contact step, 8 cubes on a slab, {n:,} tets"] = [1e3 * seconds, "ms", total]
    return results


if __name__ == "__main__":
    print("RESULT " + json.dumps(dict(solver=solver.__file__, results=measure(json.loads(sys.argv[1])))))
