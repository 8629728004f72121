"""Every figure, table and number of the lecture notes: ``python -m demo figures``.

    python -m demo figures                   # all sections (a few minutes)
    python -m demo figures --only sweeps     # one section (names: --list)
    python -m demo figures --check           # change nothing; fail if the notes or READMEs are out of date
    python -m demo figures --full            # also the 31k-tet meshes (slow: its Newton steps)

Each section below draws PNGs into ``lecture_notes/figures/`` and returns its numbers and tables,
which are stored in ``numbers.json``; then ``demo/notes_sync.py`` rewrites the marked text of the
chapters and READMEs (generated blocks, values from results files, code excerpts) and records in
``manifest.json`` what each section was drawn from, so that ``--check`` can tell a stale figure.

The measurement set-up follows ``../shared/vbd-facts.md``: a 1 x 0.1 x 0.1 m bar pinned at x = 0,
nu = 0.3, rho = 1000 kg/m^3, h = 1/60 s, gravity -9.81 z, float64 on the CPU, error
||x - x*|| / ||x* - x_n|| against the converged global Newton step x*.
"""
import json
import os
import sys
import time
from pathlib import Path

from . import notes_sync
from .notes_sync import FIGURES, NOTES, NUMBERS, chapters, stale

BAR = dict(size=(1.0, 0.1, 0.1))
CHECKPOINTS = (1, 2, 3, 5, 7, 10, 15, 20, 30, 50, 70, 100, 150, 200, 300, 500, 700, 1000)


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------
def _sci(value, digits=2):
    """1.4e-02 -> '1.4e-2'."""
    mantissa, exponent = f"{value:.{digits - 1}e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def _E(value):
    """1e+04 -> '1e4'."""
    mantissa, exponent = f"{value:.0e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def _table(header, rows):
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _material(E):
    import solver

    return solver.Material(youngs_modulus=E, poisson_ratio=0.3, density=1000.0)


def _bar_sim(cells, E, iterations=1, **kwargs):
    import solver

    mesh = solver.box_mesh(cells=cells, **BAR)
    kwargs.setdefault("initial_guess", solver.InitialGuess.INERTIAL)
    return solver.Simulation(mesh, _material(E), dt=1 / 60, fixed=mesh.vertices[:, 0] < 1e-9,
                             iterations=iterations, **kwargs)


def _convergence(sim, checkpoints, x_star=None):
    """Errors and solver seconds after each checkpoint iteration count of one step from the current state."""
    import solver

    x_n = sim.positions
    if x_star is None:
        x_star = sim.newton_reference()
    sim.begin_step()
    rows, done, seconds = [], 0, 0.0
    for k in checkpoints:
        start = time.perf_counter()
        sim.run_iterations(k - done)
        seconds += time.perf_counter() - start
        done = k
        rows.append((k, seconds, solver.relative_error(sim.positions, x_star, x_n)))
    sim.end_step()
    return rows


def _warm_up(sim):
    """Compile the step kernels so that timings measure running, not compiling; back to rest."""
    sim.begin_step()
    sim.run_iterations(1)
    sim.end_step()
    sim.reset()


def _save_image(image, path, n_colors=256):
    image = image.convert("RGB").quantize(colors=n_colors, method=2, dither=0)
    image.save(path, optimize=True)


def _save_plot(fig, path):
    import io

    from PIL import Image

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    buffer.seek(0)
    _save_image(Image.open(buffer), path, n_colors=128)
    import matplotlib.pyplot as plt

    plt.close(fig)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"font.size": 9, "axes.grid": True, "grid.alpha": 0.3, "figure.figsize": (6.4, 3.4)})
    return plt


def _render_scene(scene, frames_to_save, out, prefix, size, measure=()):
    """Run a demo scene, composing and saving only the frames asked for; returns {frame: panel states}
    of those and of the frames in `measure`.

    Every frame is simulated with its Newton ghost, so that a trajectory ghost has followed the
    converged solution all the way to the frames that are saved.
    """
    from .compose import FrameComposer
    from .runner import SceneRunner

    runner = SceneRunner(scene)
    composer = None
    wanted = sorted(set(frames_to_save) | set(measure))
    saved = {}
    for frame in range(wanted[-1] + 1):
        states = runner.advance()
        if frame in frames_to_save:
            composer = composer or FrameComposer(scene, *size)
            _save_image(composer.compose(states), out / f"{prefix}_{frame:02d}.png")
        if frame in wanted:
            saved[frame] = states
    return saved


# ---------------------------------------------------------------------------------------------
# Sections: each returns {key: text} for the notes
# ---------------------------------------------------------------------------------------------
def section_coloring(out, full, size):
    import numpy as np

    import solver
    from solver.mesh.topology import vertex_neighbours

    from . import scenes

    _render_scene(scenes.get("colouring"), [0], out, "colouring", size)
    meshes = [("bar 20x2x2 cells", solver.box_mesh(cells=(20, 2, 2), **BAR)),
              ("bar 40x4x4 cells", solver.box_mesh(cells=(40, 4, 4), **BAR)),
              ("bar 80x8x8 cells", solver.box_mesh(cells=(80, 8, 8), **BAR)),
              ("sphere, voxelised (drop scene)", scenes.get("drop").panels[0].mesh.build())]
    rows, numbers = [], {}
    for label, mesh in meshes:
        row = [label, f"{mesh.n_vertices:,}", f"{mesh.n_tets:,}"]
        for order in (solver.VertexOrder.NATURAL, solver.VertexOrder.LARGEST_FIRST):
            c = solver.color_vertices(mesh.tets, mesh.n_vertices, order)
            row.append(f"{c.n_colors} ({c.sizes.min()}-{c.sizes.max()})")
            if order is solver.VertexOrder.NATURAL and label.startswith("bar 40x4x4"):
                numbers["colouring.n_colors_40"] = str(c.n_colors)
        offsets, _ = vertex_neighbours(mesh.tets, mesh.n_vertices)
        row.append(str(int(np.diff(offsets).max())))
        rows.append(row)
    numbers["colouring.table"] = _table(
        ["mesh", "vertices", "tets", "colours, natural order (smallest-largest set)", "colours, largest first",
         "max neighbours"], rows)
    return numbers


def section_sweeps(out, full, size):
    import numpy as np

    from . import scenes

    numbers = {}
    # cells an elastic wave (speed c = sqrt(E / rho)) crosses in one time step: c h / dx
    rows = []
    for E in (1e4, 1e5, 1e6):
        c = (E / 1000.0) ** 0.5
        rows.append([f"{_E(E)} Pa", f"{c:.1f} m/s", f"{c / 60:.3f} m",
                     *[f"{c / 60 * n:.1f}" for n in (20, 40, 80)]])
    numbers["sweeps.wave.table"] = _table(["E", "c = sqrt(E / rho)", "c h (h = 1/60 s)", "c h / dx, dx = 5 cm",
                                           "dx = 2.5 cm", "dx = 1.25 cm"], rows)
    stiff = scenes.get("stiffness_sweep")
    frames = (1, 30)
    states = _render_scene(stiff, frames, out, "stiffness_sweep", size)
    errors = {f: [s.error for s in states[f]] for f in frames}
    # the soft bar stretches under gravity: the farthest vertex from the wall, against its rest distance
    rest = stiff.panels[0].mesh.build().vertices
    wall = rest[stiff.panels[0].fixed[0].select(rest)].mean(axis=0)
    reach = lambda x: np.linalg.norm(x - wall, axis=1).max()
    numbers["sweeps.stiffness.soft_stretch"] = f"{reach(states[30][0].positions) / reach(rest):.1f}"
    for frame in frames:
        for panel, error in zip(stiff.panels, errors[frame]):
            key = f"sweeps.stiffness.E{panel.material.youngs_modulus:.0e}.frame{frame}".replace("+0", "")
            numbers[key] = f"{error:.3f}"
    numbers["sweeps.stiffness.table"] = _table(
        ["frame (time)", *[f"{p.label}, {p.iterations} it." for p in stiff.panels]],
        [[f"{f} (t = {(f + 1) / 60:.2f} s)", *[f"{e:.3f}" for e in errors[f]]] for f in frames])

    res = scenes.get("resolution_sweep")
    states = _render_scene(res, frames, out, "resolution_sweep", size)
    numbers["sweeps.resolution.table"] = _table(
        ["frame (time)", *[f"{p.label}, E = {_E(p.material.youngs_modulus)} Pa, {p.iterations} it."
                           for p in res.panels]],
        [[f"{f} (t = {(f + 1) / 60:.2f} s)", *[f"{s.error:.3f}" for s in states[f]]] for f in frames])

    # the iteration sweep: distance to the converged trajectory (the picture) beside the per-step error
    sweep = scenes.get("iteration_sweep")
    shown = (5, 20, 47)
    states = _render_scene(sweep, (shown[-1],), out, "iteration_sweep", size, measure=shown)
    length = float(np.ptp(sweep.panels[0].mesh.build().vertices, axis=0).max())
    numbers["sweeps.iterations.table"] = _table(
        ["frame (time)", *[f"{p.iterations} it.: off the ghost / step error" for p in sweep.panels]],
        [[f"{f} (t = {(f + 1) * sweep.dt:.2f} s)",
          *[f"{100 * s.trajectory_gap:.0f} cm = {s.trajectory_gap / length:.2f} lengths / {s.error:.2f}"
            for s in states[f]]] for f in shown])
    return numbers


def section_convergence(out, full, size):
    import numpy as np

    import solver
    from solver.newton.direct import global_newton

    plt = _pyplot()
    meshes = [(20, 2, 2), (40, 4, 4)] + ([(80, 8, 8)] if full else [])
    results = {}
    for cells in meshes:
        for E in (1e4, 1e6):
            sim = _bar_sim(cells, E)
            _warm_up(sim)
            results[cells, E] = (sim.mesh.n_tets, _convergence(sim, CHECKPOINTS))
    fig, ax = plt.subplots()
    styles = {1e4: "-", 1e6: "--"}
    for (cells, E), (tets, rows) in results.items():
        ax.loglog([r[0] for r in rows], [max(r[2], 1e-16) for r in rows], styles[E], marker=".",
                  label=f"E = {_E(E)} Pa, {tets:,} tets")
    ax.set_xlabel("VBD iterations in the step")
    ax.set_ylabel("relative error ||x - x*|| / ||x* - x_n||")
    ax.set_title("One step from rest, initial guess y")
    ax.legend(fontsize=7)
    _save_plot(fig, out / "convergence.png")

    shown = (10, 100, 1000)
    header = ["iterations"] + [f"E = {_E(E)} Pa, {tets:,} tets" for (cells, E), (tets, _) in results.items()]
    rows = [[str(k)] + [_sci(dict((r[0], r[2]) for r in rows)[k]) for _, rows in results.values()] for k in shown]
    numbers = {"convergence.table": _table(header, rows)}
    for (cells, E), (tets, rows_) in results.items():
        by_k = {r[0]: r for r in rows_}
        for k in shown:
            numbers[f"convergence.{cells[0]}.E{E:.0e}.k{k}".replace("+0", "")] = _sci(by_k[k][2])
        numbers[f"convergence.{cells[0]}.E{E:.0e}.ms_per_iteration".replace("+0", "")] = \
            f"{1000 * by_k[1000][1] / 1000:.2f}"
    # how many sweeps per decade of error the stiff bars need, against ln(10) N_c^2 (chapters 5 and 7)
    from solver.method import wave_cells

    for cells in meshes:
        key = f"convergence.{cells[0]}.E1e6"
        tets, rows_ = results[cells, 1e6]
        by_k = {r[0]: r[2] for r in rows_}
        n_c = wave_cells(solver.box_mesh(cells=cells, **BAR), _material(1e6), 1 / 60)
        numbers[f"{key}.N_c"] = f"{n_c:.0f}"
        numbers[f"{key}.predicted_sweeps_per_decade"] = f"{np.log(10) * n_c ** 2:.0f}"
        numbers[f"{key}.measured_sweeps_per_decade"] = f"{900 / np.log10(by_k[100] / by_k[1000]):.0f}"

    # run time against error: VBD (40x4x4) against the Taichi Newton and the numpy Newton on the same step
    fig, ax = plt.subplots()
    timing_rows = []
    for E in (1e4, 1e6):
        tets, rows_ = results[(40, 4, 4), E]
        ax.loglog([r[1] for r in rows_], [max(r[2], 1e-16) for r in rows_], styles[E], marker=".",
                  label=f"VBD, E = {_E(E)} Pa")
        sim = _bar_sim((40, 4, 4), E)
        problem = sim.step_problem()
        x_n = sim.positions
        x_star = sim.newton_reference()      # also compiles the Taichi Newton's kernels before it is timed
        fast = solver.fast_newton_solve(problem, problem.y_with_constraints(), 1e-10, 50, keep_iterates=True)
        oracle = solver.newton_solve(problem, problem.y_with_constraints(), 1e-10, 50)
        seconds = [h.seconds for h in fast.history[1:]]
        errs = [max(solver.relative_error(x, x_star, x_n), 1e-16) for x in fast.iterates]
        ax.loglog(seconds, errs, styles[E], marker="s", color="k", label=f"Taichi Newton, E = {_E(E)} Pa")
        vbd_1e2 = next((r[1] for r in rows_ if r[2] <= 1e-2), None)
        vbd_1e6 = next((r[1] for r in rows_ if r[2] <= 1e-6), None)
        newton_1e2 = next(t for t, e in zip(seconds, errs) if e <= 1e-2)
        timing_rows.append([f"{_E(E)} Pa", f"{1000 * rows_[CHECKPOINTS.index(100)][1] / 100:.2f} ms",
                            "not in 1000 it." if vbd_1e2 is None else f"{1000 * vbd_1e2:.1f} ms",
                            "not in 1000 it." if vbd_1e6 is None else f"{1000 * vbd_1e6:.1f} ms",
                            f"{1000 * newton_1e2:.1f} ms", f"{fast.iterations}, {1000 * seconds[-1]:.1f} ms",
                            f"{oracle.iterations}, {1000 * oracle.history[-1].seconds:.0f} ms"])
        key = f"convergence.E{E:.0e}".replace("+0", "")
        numbers[f"{key}.newton_ms"] = f"{1000 * seconds[-1]:.1f}"
        numbers[f"{key}.numpy_newton_ms"] = f"{1000 * oracle.history[-1].seconds:.0f}"
        numbers[f"{key}.vbd_1e-2_ms"] = "-" if vbd_1e2 is None else f"{1000 * vbd_1e2:.1f}"
        numbers[f"{key}.vbd_1e-2_fraction"] = "-" if vbd_1e2 is None else f"{vbd_1e2 / seconds[-1]:.2f}"
    ax.set_xlabel("solver wall time in the step (s, this machine)")
    ax.set_ylabel("relative error")
    ax.set_title(f"Run time against error, bar 40x4x4 cells ({results[(40, 4, 4), 1e4][0]:,} tets), 1 step")
    ax.legend(fontsize=7)
    _save_plot(fig, out / "time_vs_error.png")
    numbers["convergence.timing.table"] = _table(
        ["material", "VBD time per iteration", "VBD to error 1e-2", "VBD to error 1e-6",
         "Taichi Newton to error 1e-2", "Taichi Newton: iterations, whole solve",
         "numpy Newton: iterations, whole solve"], timing_rows) + (
        f"\n\n*Measured by `.venv/bin/python -m demo figures` on {time.strftime('%Y-%m-%d')}, {os.cpu_count()} CPU "
        f"cores, load average {os.getloadavg()[0]:.1f} when the section started. VBD: time in "
        "`run_iterations` only; Newton: its whole solve, to a step below 1e-10 of the bar's size, its linear "
        f"solver {global_newton(problem.tets, problem.free).direct.kind.value}.*")
    return numbers


def section_propagation(out, full, size):
    import numpy as np

    import solver

    from . import scenes

    plt = _pyplot()
    scene = scenes.get("propagation")
    saved = (1, 5, 20, 40)
    _render_scene(scene, saved, out, "propagation", size)

    panel = scene.panels[0]
    mesh = panel.mesh.build()
    rest = mesh.vertices
    cells = panel.mesh.cells[0]
    layer = np.rint(rest[:, 0] / (panel.mesh.size[0] / cells)).astype(int)
    sim = solver.Simulation(mesh, panel.material, dt=scene.dt, gravity=scene.gravity, iterations=1,
                            fixed=panel.fixed[0].select(rest), kinematic=panel.kinematic[0].select(rest),
                            kinematic_motion=panel.motion, initial_guess=panel.initial_guess)
    x_star = sim.newton_reference()
    sim.begin_step()
    fronts, profiles = [], {}
    for k in range(1, 41):
        sim.run_iterations(1)
        moved = np.linalg.norm(sim.positions - rest, axis=1)
        reached = layer[(moved > scene.color_range[0]) & sim.free_mask]    # the pictures' threshold
        fronts.append(cells - int(reached.min()) if len(reached) else 0)
        if k in (1, 2, 5, 10, 20, 40):
            profiles[k] = np.array([moved[layer == c].max() for c in range(cells + 1)])
    sim.end_step()
    exact = np.array([np.linalg.norm(x_star - rest, axis=1)[layer == c].max() for c in range(cells + 1)])

    fig, (a, b) = plt.subplots(1, 2, figsize=(9.0, 3.4))
    xs = np.arange(cells + 1) / cells
    for k, prof in profiles.items():
        a.semilogy(xs, np.maximum(prof, 1e-17), label=f"after {k} it.")
    a.semilogy(xs, exact, "k--", label="Newton x*")
    a.set_xlabel("position along the bar (m); the right end was moved")
    a.set_ylabel("distance moved (m, log)")
    a.axhline(scene.color_range[0], color="gray", lw=0.8)
    a.set_ylim(1e-16, 0.1)
    a.legend(fontsize=7)
    ks = np.arange(1, len(fronts) + 1)
    b.plot(ks, fronts, marker=".", label="cell layers reached")
    b.plot(ks, np.minimum(ks, cells - 1), ":", color="gray", label="one layer per iteration")
    b.set_xlabel("iterations")
    b.set_ylabel(f"layers from the moved end (pinned end: {cells - 1})")
    b.legend(fontsize=7)
    fig.tight_layout()
    _save_plot(fig, out / "propagation_front.png")
    rate = np.polyfit(ks[:15], np.array(fronts[:15]), 1)[0]
    return {"propagation.front.table": _table(["iterations", *[str(k) for k in (1, 2, 3, 5, 10, 20)]],
                                              [["cell layers reached", *[str(fronts[k - 1]) for k in (1, 2, 3, 5, 10, 20)]]]),
            "propagation.rate": f"{rate:.2f}", "propagation.cells": str(cells),
            "propagation.threshold": _sci(scene.color_range[0], 1),
            "propagation.full_at": str(next((k for k, f in zip(ks, fronts) if f >= cells - 1), "more than 40"))}


def section_guesses(out, full, size):
    import solver

    plt = _pyplot()
    E, pre_steps = 1e5, 10
    sim = _bar_sim((40, 4, 4), E, iterations=200, initial_guess=solver.InitialGuess.ADAPTIVE)
    sim.step(pre_steps)
    state = sim.save_state()
    x_star = sim.newton_reference()
    checkpoints = CHECKPOINTS[:12]
    curves = {}
    for guess in solver.InitialGuess:
        sim.restore_state(state)
        sim.initial_guess = guess
        curves[guess] = _convergence(sim, checkpoints, x_star)
    fig, ax = plt.subplots()
    names = {solver.InitialGuess.PREVIOUS: "x_n", solver.InitialGuess.INERTIA: "x_n + h v_n",
             solver.InitialGuess.INERTIAL: "y = x_n + h v_n + h^2 g", solver.InitialGuess.ADAPTIVE: "adaptive"}
    for guess, rows in curves.items():
        ax.loglog([r[0] for r in rows], [r[2] for r in rows], marker=".", label=names[guess])
    ax.set_xlabel("VBD iterations in the step")
    ax.set_ylabel("relative error")
    ax.set_title(f"Initial guesses: step {pre_steps + 1} of a swinging bar, E = 1e5 Pa, 40x4x4 cells")
    ax.legend(fontsize=7)
    _save_plot(fig, out / "initial_guess.png")
    shown = (1, 10, 100)
    rows = [[f"`{g.name}`: {names[g]}", *[_sci(dict((r[0], r[2]) for r in curves[g])[k]) for k in shown]]
            for g in curves]
    return {"guesses.table": _table(["initial guess", *[f"error after {k} it." for k in shown]], rows),
            "guesses.step": str(pre_steps + 1)}


def section_chebyshev(out, full, size):
    plt = _pyplot()
    E = 1e6
    rhos = (None, 0.8, 0.9, 0.95, 0.98)
    checkpoints = CHECKPOINTS[:15]
    curves, x_star = {}, None
    for rho in rhos:
        sim = _bar_sim((40, 4, 4), E, chebyshev_rho=rho)
        x_star = sim.newton_reference() if x_star is None else x_star    # the same step for every rho
        curves[rho] = _convergence(sim, checkpoints, x_star)
    fig, ax = plt.subplots()
    for rho, rows in curves.items():
        ax.loglog([r[0] for r in rows], [r[2] for r in rows], marker=".",
                  label="no acceleration" if rho is None else f"Chebyshev, rho = {rho}")
    ax.set_xlabel("VBD iterations in the step")
    ax.set_ylabel("relative error")
    ax.set_title("Chebyshev acceleration, E = 1e6 Pa, 40x4x4 cells, one step from rest")
    ax.legend(fontsize=7)
    _save_plot(fig, out / "chebyshev.png")
    shown = (10, 100, 300)
    rows = [["none" if rho is None else str(rho), *[_sci(dict((r[0], r[2]) for r in curves[rho])[k]) for k in shown]]
            for rho in rhos]
    return {"chebyshev.table": _table(["rho", *[f"error after {k} it." for k in shown]], rows)}


def section_remedy(out, full, size):
    """Chapter 7's remedy scene: one frame of plain VBD against two-level VBD at the same wall time per
    step, and its labels as a table (the iteration count and the times are measured on this machine)."""
    import numpy as np

    from solver.method import wave_cells

    from . import scenes

    scene = scenes.get("remedy")
    frame = REMEDY_FRAME
    states = _render_scene(scene, (frame,), out, "remedy", size)[frame]
    budgets = [s.budget + (f" = {s.step_ms:.0f} ms/step" if s.step_ms is not None else "") for s in states]
    mesh = scene.panels[0].mesh.build()
    length = float(np.ptp(mesh.vertices, axis=0).max())
    numbers = {"remedy.wave_cells": f"{wave_cells(mesh, scene.panels[0].material, scene.dt):.0f}",
               "remedy.frame": str(frame), "remedy.time": f"{(frame + 1) * scene.dt:.2f}",
               "remedy.plain.budget": budgets[0], "remedy.two_level.budget": budgets[1],
               "remedy.plain.error": f"{states[0].error:.2f}", "remedy.two_level.error": _sci(states[1].error),
               "remedy.plain.gap": f"{100 * states[0].trajectory_gap:.0f}",
               "remedy.two_level.gap": f"{100 * states[1].trajectory_gap:.1f}"}
    numbers["remedy.table"] = _table(
        ["panel", "solver per step = measured wall time", "step error", "off the ghost"],
        [[p.label, budget, _sci(s.error), f"{100 * s.trajectory_gap:.1f} cm = {s.trajectory_gap / length:.0%}"]
         for p, s, budget in zip(scene.panels, states, budgets)])
    return numbers


def _short(value):
    """A residual for prose: 26, 0.28, 5.2e-5."""
    return f"{value:.2g}" if value >= 0.01 else _sci(value)


def section_newton(out, full, size):
    """Chapter 2: the largest force |dG/dx_i| after each Newton iteration on the stiff 1,920-tet bar, one
    step from rest, for projected Newton (the numpy oracle) and the Taichi Newton (eigenvalue filtering
    and chord steps). Numbers only, no figure."""
    import solver

    sim = _bar_sim((20, 4, 4), 1e6)
    problem = sim.step_problem()
    x0 = problem.y_with_constraints()
    projected = solver.newton_solve(problem, x0, 1e-10, 50)
    filtered = solver.fast_newton_solve(problem, x0, 1e-10, 50)
    numbers = {"newton.tets": f"{sim.mesh.n_tets:,}"}
    for name, result in (("projected", projected), ("filtered", filtered)):
        numbers[f"newton.{name}.residuals"] = ", ".join(_short(h.max_gradient) for h in result.history)
        numbers[f"newton.{name}.iterations"] = str(result.iterations)
    return numbers


def section_jacobi(out, full, size):
    """Chapter 4: the same per-vertex update without colours (Jacobi: every vertex from the old positions
    at once, `benchmarks/baselines.py`), plain and under-relaxed, against the coloured VBD sweep."""
    import solver

    from .errors import DemoError

    try:
        from benchmarks.baselines import JacobiSweep
    except ImportError:
        raise DemoError("the jacobi section needs benchmarks/baselines.py, which this copy of the project "
                        "does not have (a homework starter leaves benchmarks/ out); skip it with --only") from None

    plt = _pyplot()
    checkpoints = CHECKPOINTS[:14]
    fig, ax = plt.subplots()
    rows = []
    for E in (1e4, 1e6):
        sim = _bar_sim((40, 4, 4), E)
        x_n, x_star = sim.positions, sim.newton_reference()
        curves = {"coloured Gauss-Seidel (VBD)": _convergence(sim, checkpoints, x_star)}
        sim.reset()
        for omega in (1.0, 0.5):
            jacobi = JacobiSweep(sim, omega)
            sim.begin_step()
            curve, done = [], 0
            for k in checkpoints:
                jacobi.iterate(k - done)
                done = k
                curve.append((k, 0.0, solver.relative_error(sim.positions, x_star, x_n)))
            sim.reset()     # a diverged Jacobi step is dropped, not ended
            curves[f"Jacobi, omega = {omega}"] = curve
        for (label, curve), style in zip(curves.items(), ("-", "--", ":")):
            ax.loglog([r[0] for r in curve], [r[2] for r in curve], style, marker=".",
                      label=f"{label}, E = {_E(E)} Pa")
        rows += [[f"{_E(E)} Pa", label, *[_sci(dict((r[0], r[2]) for r in curve)[k]) for k in (10, 100, 200)]]
                 for label, curve in curves.items()]
    ax.set_xlabel("iterations in the step")
    ax.set_ylabel("relative error")
    ax.set_title("Without colours: Jacobi against coloured VBD, bar 40x4x4 cells, one step from rest")
    ax.legend(fontsize=7)
    _save_plot(fig, out / "jacobi.png")
    return {"jacobi.table": _table(["E", "update order", *[f"error after {k} it." for k in (10, 100, 200)]], rows)}


REMEDY_FRAME = 15      # t = 0.27 s: the plain VBD bar has sagged well below its ghost


CONTACT_FRAMES = {"pile": 30, "head_on": 13}     # the pile half a second in; the balls pressed together


def section_contact(out, full, size):
    """Chapter 8: one frame of the pile and one of the head-on collision, with their contact counts, closest
    gaps and (head-on) the step's relative error against the converged step, as numbers for the notes."""
    from . import scenes

    numbers = {}
    for name, frame in CONTACT_FRAMES.items():
        state = _render_scene(scenes.get(name), (frame,), out, f"contact_{name}", size)[frame][0]
        contact = state.lines[-1].split("; ")[0]
        numbers[f"contact.{name}.time"] = f"{(frame + 1) * scenes.get(name).dt:.2f}"
        numbers[f"contact.{name}.label"] = contact
        if state.error is not None:
            numbers[f"contact.{name}.error"] = f"{state.error:.3f}"
    scene = scenes.get("head_on")
    mesh = scene.panels[0].mesh.build()
    numbers["contact.head_on.tets"] = str(len(mesh.tets))
    numbers["contact.pile.tets"] = str(len(scenes.get("pile").panels[0].mesh.build().tets))
    numbers["contact.head_on.gap_radius"] = f"{1000 * scene.panels[0].contact.radius:.0f}"
    return numbers


SECTIONS = {
    "colouring": section_coloring,
    "jacobi": section_jacobi,
    "newton": section_newton,
    "sweeps": section_sweeps,
    "convergence": section_convergence,
    "propagation": section_propagation,
    "guesses": section_guesses,
    "chebyshev": section_chebyshev,
    "remedy": section_remedy,
    "contact": section_contact,
}


def _shown(path: Path) -> str:
    """`path` relative to the working folder when it is inside it (no absolute paths in messages)."""
    try:
        return path.resolve().relative_to(Path.cwd()).as_posix()
    except ValueError:
        return path.name


def _figures_folder(out: Path) -> Path:
    """`out`, checked to be a folder or a place for one: a file there or above it is a one-line error."""
    from .errors import DemoError

    existing = next(place for place in (out, *out.parents) if place.exists())
    if not existing.is_dir():
        raise DemoError(f"--out must be a folder, but {_shown(existing)} is a file; name a folder for the figures "
                        f"(default: lecture_notes/figures)")
    return out


def main(argv=None):
    from . import cli
    from .errors import DemoError

    parser = cli.Parser(prog="python -m demo figures",
                        description="Regenerate every figure, table and number of lecture_notes/ and the "
                                    "numbers the READMEs quote from benchmarks/results/.",
                        formatter_class=cli.HelpFormatter)
    parser.add_argument("--only", default=None, help="comma-separated sections to run (see --list; default: all); "
                                                   "'excerpts' only refreshes the code excerpts and the "
                                                   "numbers from results files")
    parser.add_argument("--list", action="store_true", help="list the sections")
    parser.add_argument("--check", action="store_true",
                        help="change nothing; exit 1 if the notes and READMEs, or the figures of the sections run "
                             "(--only), are stale")
    parser.add_argument("--full", action="store_true", help="include the 31k-tet meshes (slow)")
    parser.add_argument("--out", type=Path, default=None,
                        help="figures folder (default: this project's lecture_notes/figures)")
    parser.add_argument("--notes", type=Path, default=None,
                        help="lecture notes folder (default: this project's lecture_notes)")
    parser.add_argument("--size", type=cli.image_size, default="960x420", help="rendered frame size WxH")
    args = parser.parse_args(argv)
    if args.list:
        for name in SECTIONS:
            print(name)
        print("excerpts")
        return 0
    selected = [s for s in args.only.split(",") if s] if args.only is not None else list(SECTIONS)
    if not selected:
        raise DemoError(f"--only {args.only!r} names no section; name one or more of {', '.join(SECTIONS)}, excerpts "
                        "(see --list), or leave --only out to run them all")
    unknown = [s for s in selected if s not in SECTIONS and s != "excerpts"]
    if unknown:
        raise DemoError(f"unknown section(s) {', '.join(unknown)}; known: {', '.join(SECTIONS)}, excerpts")
    sections = list(dict.fromkeys(s for s in selected if s != "excerpts"))
    out, notes = _figures_folder(args.out or FIGURES), args.notes or NOTES
    if not chapters(notes):
        raise DemoError(f"no lecture-note chapters (NN-*.md) in {_shown(notes)}; pass --notes with the "
                        f"lecture_notes folder")
    if args.check and not out.is_dir():
        raise DemoError(f"no figures folder {args.out or _shown(out)} to check; pass --out with the figures folder "
                        "(default: lecture_notes/figures)")
    numbers_path = out / NUMBERS
    numbers = json.loads(numbers_path.read_text()) if numbers_path.exists() else {}
    width, height = args.size
    if args.check:
        # the notes' links are checked against what every section draws, so only when they are all checked
        pictures = notes_sync.stale_figures(sections, out, notes, (width, height), args.full,
                                            links=set(sections) == set(SECTIONS)) if sections else []
        problems = stale(numbers, notes) + pictures
        for line in problems:
            print(line)
        if not problems:
            print(f"notes and READMEs are up to date ({len(notes_sync.documents(notes))} documents), and so are "
                  f"the figures of {len(sections)} section(s)")
        return 1 if problems else 0
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DemoError(f"cannot create the figures folder {args.out or _shown(out)}: {e.strerror}; "
                        "choose another --out") from None
    started = time.perf_counter()
    for name in sections:
        from .cli import start_taichi

        start_taichi("cpu")
        t = time.perf_counter()
        before = notes_sync.snapshot(out)
        numbers.update(SECTIONS[name](out, args.full, (width, height)))
        numbers_path.write_text(json.dumps(numbers, indent=1, sort_keys=True) + "\n")
        notes_sync.record_section(out, name, before, (width, height), args.full)
        print(f"{name}: {time.perf_counter() - t:.1f} s", flush=True)
    changed = notes_sync.update_notes(numbers, notes)
    print(f"figures in {_shown(out)}/, {len(changed)} document(s) updated"
          + "".join(f"\n  wrote {_shown(p)}" for p in changed)
          + f"\n{time.perf_counter() - started:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
