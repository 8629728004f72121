"""Inverted tets per time step: VBD as it is vs converged Newton, on real meshes with and without slivers.

Scene (issue 11): a body hangs from its highest 5 % of vertices under gravity, E = 1e5 Pa, nu = 0.3,
rho = 1000 kg/m^3, dt = 1/60 s, VBD with 50 iterations per step and the adaptive initial guess.
The Newton trajectory is a second copy of the body advanced by a converged global Newton solve of
each step (implicit Euler with an exact solver). Per step and method the CSV holds the number of
inverted tets (det F <= 0), the smallest det F, and for VBD the inverted tets already in the
inertial prediction y of that step (before any iteration).

Meshes: `bunny` (assets/bunny.vtu, fTetWild, no slivers), `bunny_slivers` (assets/bunny_slivers.vtu,
the same surface meshed without shape optimisation), `bunny_slivers_repaired` (that mesh after
`TetMesh.without_slivers`), `sliver_box` (`solver.sliver_box_mesh`, 373 tets; what --quick runs).

    python -m benchmarks.inversion --out benchmarks/results/inversion
    python -m benchmarks.inversion --quick --out /tmp/inversion
"""
import os
import sys
import time
import warnings

import numpy as np

from benchmarks.common import (ROOT, fraction, init_taichi, output_folder, parser, positive, print_written, progress,
                               provenance, table, time_step, write_csv)

MESHES = ("bunny", "bunny_slivers", "bunny_slivers_repaired", "sliver_box")
COLUMNS = ["mesh", "tets", "slivers", "method", "step", "time", "inverted", "min_det_F", "inverted_at_y",
           "newton_iterations", "newton_converged", "seconds"]
OUTPUTS = ("inversion.csv", "inversion.png", "inversion.md")


def build_mesh(name):
    import solver

    if name == "sliver_box":
        return solver.sliver_box_mesh()
    path = os.path.join(ROOT, "assets", "bunny.vtu" if name == "bunny" else "bunny_slivers.vtu")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", solver.MeshQualityWarning)     # the slivers are the point here
        mesh = solver.load_mesh(path)
    return mesh.without_slivers() if name == "bunny_slivers_repaired" else mesh


def hanging(mesh, fraction):
    """(N,) mask of the highest `fraction` of the vertices (at least one)."""
    n = max(1, int(round(fraction * mesh.n_vertices)))
    mask = np.zeros(mesh.n_vertices, bool)
    mask[np.argsort(-mesh.vertices[:, 2], kind="stable")[:n]] = True
    return mask


def run_mesh(name, args, bar):
    import solver

    mesh = build_mesh(name)
    material = solver.Material(youngs_modulus=args.youngs_modulus, poisson_ratio=0.3, density=1000.0)
    settings = dict(mesh=mesh, material=material, dt=args.dt, fixed=hanging(mesh, args.pinned_fraction),
                    iterations=args.iterations)
    vbd = solver.Simulation(**settings)
    newton = solver.Simulation(**settings)
    rest, tets = mesh.vertices, mesh.tets
    slivers = mesh.quality().n_slivers
    rows = []

    def row(method, step, x, **extra):
        det = solver.det_F(rest, tets, x)
        rows.append(dict(mesh=name, tets=mesh.n_tets, slivers=slivers, method=method, step=step,
                         time=step * args.dt, inverted=int(np.count_nonzero(det <= 0)),
                         min_det_F=float(det.min()), **extra))

    for step in range(1, args.steps + 1):
        y = vbd.step_problem().y_with_constraints()
        start = time.perf_counter()
        vbd.step()
        row("VBD", step, vbd.positions, inverted_at_y=solver.inverted_count(rest, tets, y),
            seconds=time.perf_counter() - start)
        problem = newton.step_problem()
        x_n = newton.positions
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)      # reported in the CSV instead
            result = solver.newton_solve(problem, problem.y_with_constraints(), tolerance=1e-8,
                                         max_iterations=args.newton_iterations)
        newton.set_positions(result.x)
        newton.set_velocities((result.x - x_n) / args.dt)
        newton.time += args.dt
        newton.frame += 1
        row("Newton", step, result.x, newton_iterations=result.iterations, newton_converged=result.converged,
            seconds=time.perf_counter() - start)
        bar.update(1)
    return rows


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["mesh"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.4), squeeze=False)
    for ax, name in zip(axes[0], names):
        for method, style in (("VBD", "-"), ("Newton", "--")):
            data = [r for r in rows if r["mesh"] == name and r["method"] == method]
            ax.plot([r["step"] for r in data], [r["inverted"] for r in data], style, label=method)
        first = next(r for r in rows if r["mesh"] == name)
        ax.set_title(f"{name}\n{first['tets']} tets, {first['slivers']} slivers", fontsize=9)
        ax.set_xlabel("time step")
        ax.set_ylabel("inverted tets (det F <= 0)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def summary(rows):
    out = []
    for name in dict.fromkeys(r["mesh"] for r in rows):
        for method in ("VBD", "Newton"):
            data = [r for r in rows if r["mesh"] == name and r["method"] == method]
            out.append(dict(mesh=name, tets=data[0]["tets"], slivers=data[0]["slivers"], method=method,
                            first_step=data[0]["inverted"], max=max(r["inverted"] for r in data),
                            last=data[-1]["inverted"], min_det_F=min(r["min_det_F"] for r in data),
                            y_first_step=data[0].get("inverted_at_y", ""),
                            seconds_per_step=float(np.mean([r["seconds"] for r in data]))))
    return out


def main(argv=None):
    p = parser(__doc__.splitlines()[0], os.path.join("benchmarks", "results", "inversion"))
    p.add_argument("--meshes", nargs="+", choices=MESHES, default=["bunny_slivers", "bunny", "bunny_slivers_repaired"],
                   quick=["sliver_box"], help="which meshes")
    p.add_argument("--steps", type=positive(int), default=30, quick=5, help="time steps per mesh")
    p.add_argument("--iterations", type=positive(int), default=50, help="VBD iterations per step")
    p.add_argument("--newton-iterations", type=positive(int), default=50, help="Newton iteration cap per step")
    p.add_argument("--youngs-modulus", type=positive(float), default=1e5, help="E in Pa")
    p.add_argument("--dt", type=time_step, default=1 / 60, help="time step in s")
    p.add_argument("--pinned-fraction", type=fraction, default=0.05,
                   help="fraction of vertices pinned (the highest; at least one)")
    p.add_argument("--threads", type=positive(int), default=None, help="Taichi CPU threads (default: all)")
    args = p.parse_args(argv)
    output_folder(args, OUTPUTS)
    init_taichi(args.threads)
    rows = []
    os.makedirs(args.out, exist_ok=True)
    with progress(total=args.steps * len(args.meshes), desc="steps", disable=args.no_progress) as bar:
        for name in args.meshes:
            rows += run_mesh(name, args, bar)
            write_csv(os.path.join(args.out, "inversion.csv"), rows, COLUMNS)     # kept if a later mesh fails
    plot(rows, os.path.join(args.out, "inversion.png"))
    text = table(summary(rows), ["mesh", "tets", "slivers", "method", "y_first_step", "first_step", "max", "last",
                                 "min_det_F", "seconds_per_step"],
                 title="Inverted tets per step, hanging from the highest 5 % of vertices")
    with open(os.path.join(args.out, "inversion.md"), "w") as fh:
        fh.write(text + "\n\n" + provenance(sys.argv if argv is None else ["inversion.py"] + list(argv)) + "\n")
    print(text)
    print_written(args, OUTPUTS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
