"""Simulated frames per second of the interactive window's loop, rendering excluded.

The window advances every panel of its scene by one time step per frame (`PanelSim.step`), with or
without the Newton ghost (x* of the same step, one converged Newton solve per panel and frame). This
times exactly that loop headless, without GGUI, for a scene, and also one `Simulation` build of the
scene's first mesh after the first (kernels and adjacency shared, nothing compiled). ghost_solver names
the linear solver of the ghosts' Newton solves (`LinearSolver.AUTO`'s choice: CHOLMOD where the optional
cvxopt is installed, so say which install a quoted figure comes from).

    python -m benchmarks.interactive_fps --out benchmarks/results/interactive_fps
    python -m benchmarks.interactive_fps --quick
"""
import time

import numpy as np

from benchmarks.common import (print_written, init_taichi, output_folder, parser, positive, provenance, table, write_csv)

OUTPUTS = ("interactive_fps.csv", "summary.md")
COLUMNS = ["scene", "panels", "ghosts", "ghost_solver", "frames", "median_frame_ms", "frames_per_second",
           "first_build_s", "second_build_s"]


def ghost_solvers(panels) -> str:
    """The linear solvers of the panels' Newton ghosts, '+'-joined in panel order without repeats."""
    from solver.newton.direct import global_newton

    problems = [p.sim.step_problem() for p in panels]
    return "+".join(dict.fromkeys(global_newton(q.tets, q.free).direct.kind.value for q in problems))


def measure(scene_name: str, frames: int, ghosts: bool):
    """(row dict) for `frames` frames of the window's step loop on `scene_name`."""
    import solver
    from demo import scenes
    from demo.runner import GhostMode, PanelSim

    scene = scenes.get(scene_name)
    t = time.perf_counter()
    panels = [PanelSim(scene, p, ghost_mode=GhostMode.STEP) for p in scene.panels]
    for p in panels:
        p.ghost_enabled = ghosts
        p.step()                                   # compiles what the loop needs
    first_build = time.perf_counter() - t
    t = time.perf_counter()
    solver.Simulation(**panels[0]._settings)
    second_build = time.perf_counter() - t
    seconds = []
    for _ in range(frames):
        t = time.perf_counter()
        for p in panels:
            p.step()
        seconds.append(time.perf_counter() - t)
    median = float(np.median(seconds))
    return dict(scene=scene_name, panels=len(panels), ghosts="on" if ghosts else "off",
                ghost_solver=ghost_solvers(panels) if ghosts else "none", frames=frames,
                median_frame_ms=1e3 * median, frames_per_second=1.0 / median, first_build_s=first_build,
                second_build_s=second_build)


def main(argv=None):
    from demo.scenes import SCENES

    p = parser(__doc__.split("\n")[0], "benchmarks/results/interactive_fps")
    p.add_argument("--scenes", nargs="+", choices=list(SCENES), metavar="SCENE",
                   default=["stiffness_sweep", "resolution_sweep", "iteration_sweep"], quick=["stiffness_sweep"],
                   help=f"scenes to time, of: {', '.join(SCENES)}")
    p.add_argument("--frames", type=positive(int), default=60, quick=5,
                   help="timed frames per scene and ghost setting")
    args = p.parse_args(argv)
    out = output_folder(args, OUTPUTS)
    init_taichi()
    rows = [measure(name, args.frames, ghosts) for name in args.scenes for ghosts in (False, True)]
    text = table(rows, COLUMNS, title="Interactive loop, simulation only (rendering excluded)")
    print(text)
    write_csv(f"{out}/interactive_fps.csv", rows, COLUMNS)
    with open(f"{out}/summary.md", "w") as fh:
        fh.write(f"{provenance()}\n\n{text}\n")
    print_written(args, OUTPUTS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
