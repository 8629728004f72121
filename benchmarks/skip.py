"""Skip what a scene does not need: kernel launches, fixed vertices, set-up, iterations, frames.

Measured with Taichi's kernel profiler (which kernels a step launches, how often) and wall clocks:
  1. kernels: a plain scene (no ground, damping or Chebyshev) against scenes with each feature:
     the kernels launched per step and the time per VBD iteration. Every scene launches one kernel per
     iteration (`vbd_iteration`, all colours inside); ground, damping and Chebyshev are live settings,
     runtime branches inside it, so what a feature costs is the difference in time per iteration.
  2. fixed vertices: with half the bar pinned, the colour kernels loop over the free vertices only;
     time per iteration against the same mesh with nothing pinned; pinned positions stay bit-exact.
  3. set-up: colouring and adjacency, first Simulation on a mesh against a second one on the same
     mesh (colouring, adjacency and kernels come from the in-memory caches).
  4. stopping tolerance: a soft bar (E = 1e4 Pa, 3840 tets) stepped from rest with iterations=200 and
     tolerance=1e-4 against no tolerance: iterations run and time per step; and the price of the
     check (one residual evaluation per iteration) when a step never converges.
  5. frames: what rendering one demo frame costs (the saving for every frame not requested), if the
     demo package exposes a scene runner and composer.

    python -m benchmarks.skip --out benchmarks/results/skip
    python -m benchmarks.skip --quick --out /tmp/skip
"""
import os
import re
import time

import numpy as np

from benchmarks.common import print_written, init_taichi, output_folder, parser, positive, progress, provenance, table, write_csv

OUTPUTS = ("skip.csv", "skip.png", "summary.md")


def profiled_kernels(run):
    """{kernel name: launches} of everything `run()` launches (Taichi kernel profiler, CPU)."""
    from solver._ti import ti

    ti.sync()
    ti.profiler.clear_kernel_profiler_info()
    run()
    ti.sync()
    prof = ti.profiler.kernel_profiler.get_default_kernel_profiler()
    prof._update_records()
    prof._count_statistics()
    counts = {}
    for name, stat in prof._statistical_results.items():
        base = re.sub(r"_c\d+_\d+.*$", "", name)           # "vbd_iteration_c80_0_kernel_0_range_for" -> "vbd_iteration"
        counts[base] = max(counts.get(base, 0), stat.counter)
    return counts


def per_iteration(sim, seconds):
    sim.begin_step()
    sim.run_iterations(2)
    k, t = 1, 0.0
    while t < seconds:
        k *= 2
        start = time.perf_counter()
        sim.run_iterations(k)
        t = time.perf_counter() - start
    samples = [t / k]
    for _ in range(2):
        start = time.perf_counter()
        sim.run_iterations(k)
        samples.append((time.perf_counter() - start) / k)
    sim.end_step()
    return float(np.median(samples))


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/skip",
               quick="a 1,920-tet bar instead of 96,000 tets, and two 320x180 frames instead of five at 1280x720")
    p.add_argument("--min-seconds", type=positive(float), default=0.3, quick=0.02, help="length of each timing")
    args = p.parse_args(argv)
    output_folder(args, OUTPUTS)
    os.environ["VBD_CACHE_DIR"] = ""             # no disk cache: measure the first colouring for real
    init_taichi(kernel_profiler=True)
    import solver

    cells = (20, 4, 4) if args.quick else (40, 20, 20)
    seconds = args.min_seconds
    mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=cells)
    pinned = mesh.vertices[:, 0] < 1e-9
    mat = solver.Material(1e5, 0.3, 1000.0)
    rows = []
    bar = progress(total=5, desc="skip", disable=args.no_progress)

    # 3. set-up first (before any other Simulation on this mesh fills the colouring cache).
    t = time.perf_counter()
    first = solver.Simulation(mesh, mat, fixed=pinned, iterations=10)
    first_s = time.perf_counter() - t
    t = time.perf_counter()
    second = solver.Simulation(mesh, mat, fixed=pinned, iterations=10)
    second_s = time.perf_counter() - t
    rows.append(dict(check="set-up: colouring", scene=f"{mesh.n_tets} tets",
                     measure="seconds (1st Simulation / 2nd on the same mesh)",
                     value=f"{first.coloring.seconds:.3g} / {second.coloring.seconds:.3g}",
                     saved_s=first.coloring.seconds - second.coloring.seconds,
                     ok=(not first.coloring.cached) and second.coloring.cached))
    rows.append(dict(check="set-up: whole Simulation()", scene=f"{mesh.n_tets} tets",
                     measure="seconds (1st / 2nd; the 2nd reuses colouring, adjacency and kernels)",
                     value=f"{first_s:.3g} / {second_s:.3g}", saved_s=first_s - second_s, ok=True))
    del second
    bar.update(1)

    # 1. kernels launched per step and the cost of compiled-in features.
    plain = first
    scenes = {"plain": plain,
              "ground (no contact)": solver.Simulation(mesh, mat, fixed=pinned, iterations=10,
                                                       ground=solver.Ground(height=-10.0)),
              "damping": solver.Simulation(mesh, mat, fixed=pinned, iterations=10, damping=1e-3),
              "Chebyshev": solver.Simulation(mesh, mat, fixed=pinned, iterations=10, chebyshev_rho=0.9)}
    times = {}
    for name, sim in scenes.items():
        sim.step()                                                # compile
        kernels = profiled_kernels(lambda: sim.step())
        times[name] = per_iteration(sim, seconds)
        rows.append(dict(check="kernels per step (10 iterations)", scene=name, measure="kernel: launches",
                         value=", ".join(f"{k}: {v}" for k, v in sorted(kernels.items())),
                         time_per_iteration_ms=times[name] * 1e3,
                         saved_s=(times[name] - times["plain"]) if name != "plain" else 0.0,
                         ok=kernels.get("vbd_iteration") == 10))
    bar.update(1)

    # 2. fixed vertices.
    half = mesh.vertices[:, 0] < 0.5 - 1e-9
    pinned_half = solver.Simulation(mesh, mat, fixed=half, iterations=10)
    nothing = solver.Simulation(mesh, mat, fixed=None, iterations=10, gravity=(0, 0, 0))
    pinned_half.step()
    nothing.step()
    x_before = pinned_half.positions[half]
    pinned_half.step(3)
    exact = bool((pinned_half.positions[half] == x_before).all())
    t_half, t_none = per_iteration(pinned_half, seconds), per_iteration(nothing, seconds)
    rows.append(dict(check="fixed vertices", scene=f"{half.sum()} of {mesh.n_vertices} pinned",
                     measure="slots iterated; ms/iteration (half pinned / none pinned)",
                     value=f"{pinned_half.topology.n_slots} slots = {int((~half).sum())} free vertices; "
                           f"{t_half * 1e3:.3g} / {t_none * 1e3:.3g} ms",
                     time_per_iteration_ms=t_half * 1e3, saved_s=t_none - t_half,
                     ok=exact and pinned_half.topology.n_slots == int((~half).sum())))
    del pinned_half, nothing
    bar.update(1)

    # 4. stopping tolerance: a soft bar's first step from rest converges well inside the cap.
    soft = solver.Material(1e4, 0.3, 1000.0)
    bar_mesh = solver.box_mesh(size=(1.0, 0.1, 0.1), cells=(40, 4, 4))
    settle = solver.Simulation(bar_mesh, soft, fixed=bar_mesh.vertices[:, 0] < 1e-9, iterations=200)
    results = {}
    for tol in (None, 1e-4):
        settle.tolerance = tol
        settle.reset()
        settle.step()   # warm-up
        settle.reset()
        t = time.perf_counter()
        settle.step()
        results[tol] = (time.perf_counter() - t, settle.last_iterations)
    rows.append(dict(check="stopping tolerance", scene=f"E=1e4 bar, {bar_mesh.n_tets} tets, 1st step, iterations=200",
                     measure="iterations, seconds per step (no tolerance / tolerance=1e-4)",
                     value=f"{results[None][1]} it {results[None][0]:.3g} s / "
                           f"{results[1e-4][1]} it {results[1e-4][0]:.3g} s",
                     saved_s=results[None][0] - results[1e-4][0], ok=results[1e-4][1] < results[None][1]))
    # the price of the check when the step does not converge: residual evaluated every iteration
    settle.tolerance = 1e-30
    settle.iterations = 10
    t_check = per_iteration(settle, seconds)
    settle.tolerance = None
    t_plain = per_iteration(settle, seconds)
    rows.append(dict(check="stopping tolerance: cost of the check", scene=f"same {bar_mesh.n_tets} tets, never converging",
                     measure="ms/iteration (tolerance set / none)",
                     value=f"{t_check * 1e3:.3g} / {t_plain * 1e3:.3g} ms", time_per_iteration_ms=t_check * 1e3,
                     saved_s=t_plain - t_check, ok=True))
    bar.update(1)

    # 5. frames not requested.
    rows.append(frame_cost(args.quick))
    bar.update(1)
    bar.close()

    cols = ["check", "scene", "measure", "value", "time_per_iteration_ms", "saved_s", "ok"]
    write_csv(os.path.join(args.out, "skip.csv"), rows, cols)
    plot(times, os.path.join(args.out, "skip.png"), mesh.n_tets)
    text = table(rows, cols, f"What a scene skips ({mesh.n_tets} tets; saved_s < 0 means the feature costs "
                 "that much per iteration or per step)")
    with open(os.path.join(args.out, "summary.md"), "w") as fh:
        fh.write(f"Produced by {provenance()}.\n\n{text}\n")
    print(text)
    print_written(args, OUTPUTS)
    return rows


def frame_cost(quick):
    """Seconds to render one demo frame against seconds to simulate it."""
    from demo import scenes
    from demo.compose import FrameComposer
    from demo.runner import SceneRunner

    scene = scenes.get(scenes.DEFAULT_SCENE)
    runner = SceneRunner(scene)
    composer = FrameComposer(scene, 320 if quick else 1280, 180 if quick else 720)
    states = runner.advance()
    composer.compose(states)                      # compile
    n = 2 if quick else 5
    t = time.perf_counter()
    for _ in range(n):
        states = runner.advance()
    sim_s = (time.perf_counter() - t) / n
    t = time.perf_counter()
    for _ in range(n):
        composer.compose(states)
    draw_s = (time.perf_counter() - t) / n
    return dict(check="frames not requested", scene=f"demo '{scene.name}'",
                measure="seconds per frame: simulate / render (saved per frame not rendered)",
                value=f"{sim_s:.3g} / {draw_s:.3g}", saved_s=draw_s, ok=True)


def plot(times, path, n_tets):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.2))
    names = list(times)
    ax.barh(names, [times[n] * 1e3 for n in names], color=["k"] + ["tab:blue"] * (len(names) - 1))
    ax.set_xlabel(f"ms per VBD iteration ({n_tets} tets)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    main()
