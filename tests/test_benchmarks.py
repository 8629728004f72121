"""The benchmarks' --quick modes run and write sane CSVs; the baselines agree with the solver;
a few stress-grid cells that run in seconds stay as regular tests. No timings are asserted."""
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from tests.benchmark_checks import benchmark_module, exits_with_one_line, rows

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run_quick(module, out, *options):
    proc = subprocess.run([sys.executable, "-m", f"benchmarks.{module}", "--quick", "--no-progress", *options,
                           "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "|" in proc.stdout            # the printed summary table
    files = benchmark_module(module).OUTPUTS
    assert proc.stdout.strip().splitlines()[-1] == f"wrote {', '.join(files)} into {out}"   # what it wrote, last
    return proc.stdout




@pytest.mark.slow
def test_pareto_quick(tmp_path):
    run_quick("pareto", tmp_path)
    data = rows(tmp_path / "pareto.csv")
    assert {"case", "method", "iterations", "seconds", "error", "energy_gap"} <= set(data[0])
    assert (tmp_path / "pareto.png").stat().st_size > 0
    methods = {r["method"] for r in data}
    assert {"VBD", "numpy VBD", "Newton", "Jacobi omega=1"} <= methods
    # the global channels of chapter 7: numpy twin of the fast Newton, Newton-PCG, two-level VBD
    assert {"numpy Newton", "Newton-PCG (color_sweep)", "Newton-PCG (block_jacobi)", "two-level VBD"} <= methods
    assert {"newton", "numpy_newton", "pcg", "multilevel"} <= {r["family"] for r in data}
    for case in {r["case"] for r in data}:
        vbd = [r for r in data if r["case"] == case and r["method"] == "VBD"]
        errors = [float(r["error"]) for r in vbd]
        assert errors[-1] < 1e-6 * errors[0]            # VBD converges to the Newton solution
        assert all(float(r["seconds"]) >= 0 for r in vbd)
        gaps = [float(r["energy_gap"]) for r in vbd]
        assert min(gaps) > -1e-8                         # x* minimises G: nobody goes below it
        newton = [r for r in data if r["case"] == case and r["method"] == "Newton"]
        assert float(newton[-1]["error"]) == 0.0         # its last iterate is x* itself
        for method in ("numpy Newton", "Newton-PCG (color_sweep)", "Newton-PCG (block_jacobi)", "two-level VBD"):
            curve = [r for r in data if r["case"] == case and r["method"] == method]
            errors = [float(r["error"]) for r in curve]
            assert errors[-1] < 1e-6 * errors[0], method    # each reaches the fast Newton's x*
            seconds = [float(r["seconds"]) for r in curve]
            assert seconds == sorted(seconds) and seconds[-1] > 0, method
        numpy_vbd = [r for r in data if r["case"] == case and r["method"] == "numpy VBD"]
        # same sweep, same iterates: the numpy errors equal the Taichi ones at the same iteration count
        by_it = {r["iterations"]: float(r["error"]) for r in vbd}
        for r in numpy_vbd:
            if r["iterations"] in by_it and by_it[r["iterations"]] > 1e-9:
                assert float(r["error"]) == pytest.approx(by_it[r["iterations"]], rel=1e-6)


@pytest.mark.slow
def test_throughput_quick(tmp_path):
    run_quick("throughput", tmp_path)
    data = rows(tmp_path / "throughput.csv")
    assert {"tets", "precision", "threads", "n_colors", "ns_per_tet_iter", "coloring_s", "setup_s",
            "numpy_ns_per_tet_iter", "newton_iter_s", "fast_newton_iter_s"} <= set(data[0])
    assert {(r["precision"], r["threads"]) for r in data} == {("float64", "1"), ("float64", "2"),
                                                              ("float32", "1"), ("float32", "2")}
    for r in data:
        assert 4 <= int(r["n_colors"]) <= 64
        assert float(r["ns_per_tet_iter"]) > 0 and math.isfinite(float(r["ns_per_tet_iter"]))
    assert any(r["numpy_ns_per_tet_iter"] for r in data)
    newton = [r for r in data if r["fast_newton_iter_s"]]
    assert newton and all(float(r["fast_newton_iter_s"]) > 0 and float(r["newton_iter_s"]) > 0 for r in newton)
    fits = rows(tmp_path / "scaling_fit.csv")
    assert all(math.isfinite(float(f["exponent_all"])) for f in fits)
    assert (tmp_path / "throughput.png").exists()


@pytest.mark.backend
def test_stability_quick(tmp_path, capsys, arch):
    """In this process, with the threads Taichi already runs with (another count would mean a new ti.init,
    which frees every array made before it)."""
    import solver
    from solver._ti import running_config

    if arch != "cpu":
        pytest.skip("the stability benchmark runs on the CPU only: a CUDA run would be initialised again")
    solver.ensure_taichi("cpu")
    threads = running_config().cpu_max_num_threads
    stability = benchmark_module("stability")
    stability.main(["--quick", "--no-progress", "--threads", str(threads), "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert "|" in out and out.strip().splitlines()[-1] == f"wrote {', '.join(stability.OUTPUTS)} into {tmp_path}"
    data = rows(tmp_path / "stability.csv")
    assert {"dt", "E", "nu", "state", "finite", "monotone", "recovers", "error"} <= set(data[0])
    assert {r["state"] for r in data} == {"rest", "noise", "inverted", "flat", "velocity"}
    assert all(r["finite"] == "True" and r["monotone"] == "True" for r in data)
    assert (tmp_path / "stability.png").exists()


@pytest.mark.slow
@pytest.mark.backend
def test_contact_quick(tmp_path):
    run_quick("contact", tmp_path)
    data = rows(tmp_path / "contact.csv")
    balls, cubes = ([r for r in data if r["measurement"] == f"{shape} pile"] for shape in ("ball", "cube"))
    for piles in (balls, cubes):
        assert [int(r["bodies"]) for r in piles] == [1, 8]
        assert all(int(r["contacts"]) > 0 for r in piles), "a settled pile touches its box"
        assert int(piles[1]["contacts"]) > int(piles[0]["contacts"])
    assert int(balls[1]["tets"]) > int(cubes[1]["tets"])
    assert [int(r["body_tets"]) for r in (balls[0], cubes[0])] == [114, 48]
    (fine,) = [r for r in data if r["measurement"] == "fine ball pile"]      # --quick: resolution 4, one ball
    assert int(fine["bodies"]) == 1 and int(fine["body_tets"]) == 192 and int(fine["contacts"]) > 0
    assert int(fine["tets"]) - int(fine["body_tets"]) == int(balls[0]["tets"]) - 114, "the same box"
    piles = balls + cubes + [fine]
    (apart,) = [r for r in data if r["measurement"].startswith("apart")]
    assert int(apart["contacts"]) == 0, "bodies set apart have no pair closer than the radius"
    (touching,) = [r for r in data if r["measurement"].startswith("touching")]
    assert int(touching["contacts"]) > 0, "bodies 1.5 mm apart are inside the 2 mm radius"
    for r in data:
        assert float(r["detect_ms"]) > 0 and float(r["sweep_ms"]) > 0
    for r in piles:
        assert float(r["step_ms"]) > 0 and float(r["apart_step_ms"]) > 0
    assert float(apart["ns_per_tet_iter_none"]) > 0 and float(apart["ns_per_tet_iter_contact"]) > 0
    assert (tmp_path / "contact.png").stat().st_size > 0


@pytest.mark.slow
@pytest.mark.backend
def test_newton_contact_quick(tmp_path):
    """head_on's first 22 steps: with the exact pair Hessians no Newton solve reaches the cap and they take
    fewer iterations in all than with the PSD parts only; solves that converge reach the same solution."""
    run_quick("newton_contact", tmp_path)
    data = rows(tmp_path / "newton_contact.csv")
    for kind in {r["linear_solver"] for r in data}:
        exact, psd = ([r for r in data if r["linear_solver"] == kind and r["pair_hessian"] == h]
                      for h in ("exact", "psd"))
        assert len(exact) == len(psd) == 22
        assert any(int(r["contacts"]) > 0 for r in exact), "the balls meet within the quick run"
        assert all(r["converged"] == "True" for r in exact)
        assert sum(int(r["iterations"]) for r in exact) < 0.75 * sum(int(r["iterations"]) for r in psd)
        assert all(int(r["evaluations"]) > int(r["iterations"]) for r in exact)
        for r in psd:
            if r["converged"] == "True":
                assert float(r["x_vs_exact"]) < 1e-2
    assert (tmp_path / "newton_contact.png").stat().st_size > 0


def test_provenance_names_the_commit_and_says_when_the_code_was_edited(tmp_path):
    """A results file names the commit it was measured on; edited code makes that a lie unless said. New
    results beside it (benchmarks/results) are not an edit."""
    from benchmarks.common import provenance

    def git(*args):
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path, check=True,
                       capture_output=True)

    (tmp_path / "benchmarks" / "results").mkdir(parents=True)
    (tmp_path / "solver.py").write_text("a = 1\n")
    (tmp_path / "benchmarks" / "results" / "r.csv").write_text("x\n1\n")
    git("init", "-q")
    git("add", "-A")
    git("commit", "-qm", "first")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=tmp_path, capture_output=True,
                            text=True).stdout.strip()
    (tmp_path / "benchmarks" / "results" / "r.csv").write_text("x\n2\n")
    assert f"commit {commit}, " in provenance(["throughput.py"], root=tmp_path)
    (tmp_path / "solver.py").write_text("a = 2\n")
    assert f"commit {commit} with uncommitted changes, " in provenance(["throughput.py"], root=tmp_path)
    # Newton timings depend on whether the optional CHOLMOD is there: the line says
    from solver.newton.direct import DirectSolver, LinearSolver
    cholmod = "with" if DirectSolver.installed(LinearSolver.CHOLMOD) else "without"
    assert provenance(["throughput.py"], root=tmp_path).endswith(f" CPU cores, {cholmod} CHOLMOD (cvxopt)")


def test_skip_quick(tmp_path):
    run_quick("skip", tmp_path, "--min-seconds", "0.001")     # the checks, not the timings
    data = rows(tmp_path / "skip.csv")
    by_check = {}
    for r in data:
        by_check.setdefault(r["check"], []).append(r)
    for r in by_check["kernels per step (10 iterations)"]:
        assert "vbd_iteration: 10" in r["value"] and r["ok"] == "True", r     # one launch per iteration
    assert by_check["fixed vertices"][0]["ok"] == "True"
    assert by_check["set-up: colouring"][0]["ok"] == "True"
    assert by_check["stopping tolerance"][0]["ok"] == "True"
    from demo.scenes import DEFAULT_SCENE

    (frames,) = by_check["frames not requested"]          # measured, not "demo API differs"
    assert frames["ok"] == "True" and frames["scene"] == f"demo '{DEFAULT_SCENE}'", frames


# ---------------------------------------------------------------------------------------------
# In-process checks (no subprocess): baselines and stress cells that run in seconds.
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def solver_module():
    import solver

    solver.ensure_taichi("cpu")
    return solver


def test_a_benchmark_run_in_process_keeps_the_running_taichi(solver_module):
    """ti.init would free every array of the process (the tests' simulations and caches): a benchmark's
    main() called where Taichi already runs with its settings keeps it."""
    from benchmarks.common import init_taichi
    from solver._ti import runtime

    running, arch = runtime(), "cpu" if solver_module.backend.running_on_cpu() else "gpu"
    init_taichi(arch=arch)
    init_taichi(threads=None, kernel_profiler=False, arch=arch)
    assert runtime() is running


@pytest.mark.backend
def test_numpy_vbd_matches_taichi_sweep(solver_module):
    solver = solver_module
    from benchmarks.baselines import NumpyVBD

    mesh = solver.box_mesh(size=(1, .1, .1), cells=(10, 2, 2))
    sim = solver.Simulation(mesh, solver.Material(1e5, 0.3, 1000.0), fixed=mesh.vertices[:, 0] < 1e-9,
                            iterations=5)
    sim.step()
    sim.begin_step()
    x0, y = sim.positions, sim.y
    sim.run_iterations(5)
    x_taichi = sim.positions
    sim.end_step()
    x_numpy = NumpyVBD(sim).sweep(x0, y, 5)
    assert np.abs(x_numpy - x_taichi).max() < 1e-12


@pytest.mark.backend
def test_jacobi_without_coloring_is_worse(solver_module):
    """Updating all vertices at once from the same old positions overshoots: plain Jacobi ends far
    from x*, where the coloured sweep converges."""
    solver = solver_module
    from benchmarks.baselines import JacobiSweep

    mesh = solver.box_mesh(size=(1, .1, .1), cells=(10, 2, 2))
    sim = solver.Simulation(mesh, solver.Material(1e4, 0.3, 1000.0), fixed=mesh.vertices[:, 0] < 1e-9)
    x_n, x_star = sim.positions, sim.newton_reference()
    sim.begin_step()
    JacobiSweep(sim, 1.0).iterate(60)
    err_jacobi = solver.relative_error(sim.positions, x_star, x_n)
    sim.end_step()
    sim.reset()
    sim.begin_step()
    sim.run_iterations(60)
    err_vbd = solver.relative_error(sim.positions, x_star, x_n)
    sim.end_step()
    assert err_vbd < 1e-6 and err_jacobi > 1e3 * err_vbd


@pytest.fixture(scope="module")
def stress_runner(solver_module):
    from benchmarks.stability import RESOLUTIONS, Runner

    return Runner(RESOLUTIONS["coarse"], iterations=20, steps=3, recovery_rounds=5, recovery_iterations=200)


@pytest.mark.backend
@pytest.mark.parametrize("dt,E,nu,state", [
    (1 / 60, 1e4, 0.3, "rest"),
    (1 / 60, 1e4, 0.3, "noise"),
    (1 / 60, 1e4, 0.3, "inverted"),
    (1 / 10, 1e10, 0.45, "flat"),
    (1 / 1000, 1e3, 0.0, "velocity"),
    (1 / 10, 1e8, 0.499, "noise"),
])
def test_stress_cell_stays_finite_and_monotone(stress_runner, dt, E, nu, state):
    out = stress_runner.cell(dt, E, nu, state)
    assert out["finite"]
    assert out["monotone"], out["max_rise"]


@pytest.mark.backend
@pytest.mark.parametrize("state", ["rest", "noise", "inverted"])
def test_stress_cell_recovers_rest_shape(stress_runner, state):
    out = stress_runner.cell(1 / 60, 1e4, 0.3, state)
    assert out["recovers"], out


# ---------------------------------------------------------------------------------------------
# Output folders and arguments: quick runs never touch the committed results, nothing is replaced
# without --overwrite, bad values end in one line. Only argument handling runs here, no benchmark.
# ---------------------------------------------------------------------------------------------
SCRIPTS = ("pareto", "throughput", "stability", "skip", "render_speed", "contact", "newton_contact")


def test_quick_runs_write_into_a_new_scratch_folder_full_runs_into_the_results(tmp_path):
    import tempfile

    from benchmarks.common import output_folder, parser

    results = tmp_path / "results"
    p = parser("test", str(results))
    quick = [output_folder(p.parse_args(["--quick"]), ["a.csv"]) for _ in range(2)]
    assert quick[0] != quick[1] and all(os.path.dirname(q) == tempfile.gettempdir() for q in quick)
    assert not results.exists()
    assert output_folder(p.parse_args([]), ["a.csv"]) == str(results) and results.is_dir()
    for q in quick:
        os.rmdir(q)


@pytest.mark.parametrize("name", SCRIPTS)
def test_no_benchmark_replaces_results_without_overwrite(tmp_path, capsys, name):
    module = benchmark_module(name)
    first = tmp_path / module.OUTPUTS[0]
    first.write_text("committed")
    exits_with_one_line(capsys, lambda: module.main(["--quick", "--out", str(tmp_path)]),
                         "already exist; pass --overwrite")
    assert first.read_text() == "committed"


@pytest.mark.parametrize("argv, match", [
    (["--out", ""], "--out is empty"),
    (["--out", "/proc/x"], "cannot create output folder /proc/x"),
])
@pytest.mark.parametrize("name", SCRIPTS)
def test_unusable_output_folder_gives_one_line_errors(capsys, name, argv, match):
    exits_with_one_line(capsys, lambda: benchmark_module(name).main(["--quick"] + argv), match)


# Every benchmark module (those with a main()), and a bad value for every option that takes one.
BENCHMARKS = sorted(name[:-3] for name in os.listdir(os.path.join(ROOT, "benchmarks")) if name.endswith(".py")
                    and "\ndef main(" in open(os.path.join(ROOT, "benchmarks", name)).read())
BAD_VALUES = [
    ("pareto", ["--budget", "-1"], "--budget: expected a positive number, got '-1'"),
    ("pareto", ["--max-iterations", "0"], "--max-iterations: expected a positive whole number"),
    ("pareto", ["--max-cycles", "1.5"], "--max-cycles: expected a positive whole number"),
    ("pareto", ["--frames", "0"], "--frames: expected a positive whole number"),
    ("pareto", ["--rhos", "0.9", "1.5"], "between 0 and 1"),
    ("pareto", ["--threads", "0"], "--threads: expected a positive whole number"),
    ("throughput", ["--threads", "1", "-2"], "--threads: expected a positive whole number, got '-2'"),
    ("throughput", ["--min-seconds", "0"], "--min-seconds: expected a positive number"),
    ("throughput", ["--newton-max-tets", "nan"], "--newton-max-tets: expected a positive whole number"),
    ("throughput", ["--max-tets", "-5"], "--max-tets: expected a positive whole number"),
    ("stability", ["--iterations", "0"], "--iterations: expected a positive whole number"),
    ("stability", ["--steps", "x"], "--steps: expected a positive whole number"),
    ("stability", ["--recovery-rounds", "-1"], "--recovery-rounds: expected a positive whole number"),
    ("stability", ["--recovery-iterations", "0"], "--recovery-iterations: expected a positive whole number"),
    ("stability", ["--threads", "0"], "--threads: expected a positive whole number"),
    ("skip", ["--min-seconds", "nan"], "--min-seconds: expected a positive number"),
    ("newton_speed", ["--repeats", "0"], "--repeats: expected a positive whole number"),
    ("newton_speed", ["--budget", "inf"], "--budget: expected a positive number"),
    ("newton_speed", ["--threads", "-2"], "--threads: expected a positive whole number"),
    ("multilevel", ["--sizes", "1", "0"], "--sizes: expected a positive whole number, got '0'"),
    ("multilevel", ["--moduli", "-1"], "--moduli: expected a positive number"),
    ("multilevel", ["--states", "rest", "fast"], "--states: invalid choice: 'fast'"),
    ("multilevel", ["--coarsening", "0"], "--coarsening: expected a positive whole number"),
    ("multilevel", ["--cycles", "0"], "--cycles: expected a positive whole number"),
    ("multilevel", ["--max-sweeps", "0"], "--max-sweeps: expected a positive whole number"),
    ("multilevel", ["--frames", "-1"], "--frames: expected a positive whole number"),
    ("multilevel", ["--repeats", "0"], "--repeats: expected a positive whole number"),
    ("multilevel", ["--newton-max-tets", "0"], "--newton-max-tets: expected a positive whole number"),
    ("multilevel", ["--reference-cycles", "0"], "--reference-cycles: expected a positive whole number"),
    ("inversion", ["--meshes", "dragon"], "--meshes: invalid choice: 'dragon'"),
    ("inversion", ["--steps", "0"], "--steps: expected a positive whole number"),
    ("inversion", ["--iterations", "0"], "--iterations: expected a positive whole number"),
    ("inversion", ["--newton-iterations", "0"], "--newton-iterations: expected a positive whole number"),
    ("inversion", ["--youngs-modulus", "nan"], "--youngs-modulus: expected a positive number"),
    ("inversion", ["--dt", "-1"], "--dt: expected a time step between 1e-09 and 1000 seconds"),
    ("inversion", ["--dt", "1e4"], "--dt: expected a time step between 1e-09 and 1000 seconds"),
    ("inversion", ["--pinned-fraction", "2"], "--pinned-fraction: expected a fraction greater than 0 and at most 1"),
    ("inversion", ["--threads", "0"], "--threads: expected a positive whole number"),
    ("interactive_fps", ["--scenes", "nosuch"], "--scenes: invalid choice: 'nosuch'"),
    ("interactive_fps", ["--frames", "0"], "--frames: expected a positive whole number"),
    ("contact", ["--settle", "0"], "--settle: expected a positive whole number"),
    ("contact", ["--steps", "0"], "--steps: expected a positive whole number"),
    ("contact", ["--min-seconds", "-1"], "--min-seconds: expected a positive number"),
    ("contact", ["--cells", "0"], "--cells: expected a positive whole number"),
    ("contact", ["--fine-resolution", "1"], "--fine-resolution: expected a whole number from 2 to 1000"),
    ("newton_contact", ["--frames", "-3"], "--frames: expected a positive whole number"),
    ("translation_lag", ["--settle", "0"], "--settle: expected a positive whole number"),
    ("render_speed", ["--frames", "0"], "--frames: expected a positive whole number"),
    ("render_speed", ["--size", "10"], "WIDTHxHEIGHT"),
    ("render_speed", ["--cells", "1,2"], "three positive whole numbers"),
    ("render_speed", ["--arch", "tpu"], "--arch: invalid choice: 'tpu'"),
    ("cuda", ["--arch", "metal"], "--arch: invalid choice: 'metal'"),
    ("cuda", ["--max-tets", "0"], "--max-tets: expected a positive whole number"),
    ("cuda", ["--arch", "cpu", "--max-tets", "100"], "--max-tets 100 leaves no box: the smallest has 144 tets"),
    ("cuda", ["--pile", "1.5"], "--pile: expected a positive whole number"),
    ("cuda", ["--steps", "-1"], "--steps: expected a positive whole number"),
    ("cuda", ["--cells", "x"], "--cells: expected a positive whole number"),
    ("cuda", ["--min-seconds", "inf"], "--min-seconds: expected a positive number"),
    ("cuda", ["--parts", "sweep", "all"], "--parts: invalid choice: 'all'"),
    ("before_after", ["--against", "no-such-commit"], "'no-such-commit' is neither a folder nor a commit of this"),
    ("before_after", ["--rounds", "0"], "--rounds: expected a positive whole number"),
    ("before_after", ["--parts", "vbd", "pareto"], "--parts: invalid choice: 'pareto'"),
    ("before_after", ["--frames", "-1"], "--frames: expected a positive whole number"),
]


@pytest.mark.parametrize("name, argv, match", BAD_VALUES, ids=[f"{n} {' '.join(a)}" for n, a, _ in BAD_VALUES])
def test_bad_benchmark_arguments_give_one_line_errors(capsys, name, argv, match):
    """Nonsense is an argparse error (exit 2, one line) before anything runs, not a traceback from the
    solver or a benchmark that silently runs something else."""
    exits_with_one_line(capsys, lambda: benchmark_module(name).main(["--quick"] + argv), match)


@pytest.mark.parametrize("name", BENCHMARKS)
def test_every_option_that_takes_a_value_has_a_bad_value_case(capsys, name):
    with pytest.raises(SystemExit):
        benchmark_module(name).main(["--help"])
    options = set(re.findall(r"^  (--[\w-]+) \S", capsys.readouterr().out, re.M)) - {"--out"}
    assert options and options == {argv[0] for module, argv, _ in BAD_VALUES if module == name}


@pytest.mark.backend
def test_render_speed_quick(tmp_path, capsys):
    benchmark_module("render_speed").main(["--quick", "--out", str(tmp_path)])
    data = rows(tmp_path / "render_speed.csv")
    assert len(data) == 3 and all(float(r["render_ms"]) > 0 for r in data)
    assert (tmp_path / "render_speed_frame.png").stat().st_size > 0
    out = capsys.readouterr().out
    assert "[Taichi]" not in out
    assert out.strip().splitlines()[-1] == f"wrote render_speed.csv, render_speed_frame.png into {tmp_path}"


@pytest.mark.backend
def test_render_speed_quick_keeps_the_size_and_frames_given(tmp_path, capsys):
    from PIL import Image

    benchmark_module("render_speed").main(["--quick", "--no-progress", "--out", str(tmp_path), "--size", "64x48",
                                           "--frames", "2"])
    assert len(rows(tmp_path / "render_speed.csv")) == 2
    assert Image.open(tmp_path / "render_speed_frame.png").size == (64, 48)
    assert capsys.readouterr().out.startswith("64x48, ")


@pytest.mark.backend
@pytest.mark.filterwarnings("ignore:arch=.* was asked for")
def test_render_speed_names_the_backend_that_ran_not_the_one_asked_for(tmp_path, capsys, solver_module):
    """--arch gpu without CUDA renders on the CPU (as here: the other backend than the one running), and its
    summary said arch=gpu."""
    ran = "cpu" if solver_module.backend.running_on_cpu() else "gpu"
    other = {"cpu": "gpu", "gpu": "cpu"}[ran]
    benchmark_module("render_speed").main(["--quick", "--no-progress", "--out", str(tmp_path), "--arch", other])
    assert f" arch={ran}: " in capsys.readouterr().out


@pytest.mark.parametrize("name", SCRIPTS + ("newton_speed", "multilevel", "inversion", "interactive_fps",
                                           "before_after"))
def test_help_names_the_command(capsys, name):
    module = benchmark_module(name)
    with pytest.raises(SystemExit) as stop:
        module.main(["--help"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: python -m benchmarks.{name} ")


def help_entries(text):
    """{option: (what it takes, its help)} of the options in an argparse --help output."""
    entries, option = {}, None
    for line in text.split("options:", 1)[1].splitlines():
        if re.match(r"  -", line):
            invocation, _, help = line.strip().partition("  ")
            option, _, takes = invocation.split(", ")[-1].partition(" ")
            entries[option] = [takes, help]
        elif option:
            entries[option][1] += " " + line
    return {option: (takes, " ".join(help.split())) for option, (takes, help) in entries.items()}


@pytest.mark.parametrize("name", BENCHMARKS)
def test_help_says_what_every_option_does_and_its_default(capsys, name):
    with pytest.raises(SystemExit):
        benchmark_module(name).main(["--help"])
    for option, (takes, help) in help_entries(capsys.readouterr().out).items():
        assert len(help.split()) >= 3, f"{option} has no help: {help!r}"
        assert not takes or "default" in help, f"{option} does not say its default: {help!r}"
        assert "default: [" not in help, f"{option} shows its default as a Python list: {help!r}"


@pytest.mark.parametrize("name", BENCHMARKS)
def test_quick_help_says_what_it_sets(capsys, name):
    with pytest.raises(SystemExit):
        benchmark_module(name).main(["--help"])
    entries = help_entries(capsys.readouterr().out)
    quick = entries.pop("--quick")[1]
    assert quick.startswith("a small, fast version (what the tests run): "), quick
    for option, (_, help) in entries.items():
        value = re.search(r"; --quick: (.*)\)$", help)
        assert not value or f"{option} {value[1]}" in quick, (option, quick)
        assert "not with --quick" not in help or f"not with {option}" in quick, (option, quick)


def test_quick_sets_only_the_options_not_given(tmp_path):
    from benchmarks.common import parser, positive

    p = parser("test", str(tmp_path / "results"))
    p.add_argument("--count", type=positive(int), default=5, quick=1, help="a count")
    p.add_argument("--names", type=lambda text: text.split(","), default="a,b", quick="c", help="names")
    full, quick = p.parse_args([]), p.parse_args(["--quick"])
    assert (full.count, full.names) == (5, ["a", "b"]) and (quick.count, quick.names) == (1, ["c"])
    assert p.parse_args(["--quick", "--count", "3"]).count == 3
    assert p.parse_args(["--names", "d", "--quick"]).names == ["d"]


@pytest.mark.parametrize("name, argv, match", [
    ("stability", ["--all"], "--all cannot be used with --quick: it runs a few cells of the coarse mesh; drop one"),
    ("pareto", ["--frames", "5"], "--frames cannot be used with --quick: it runs no 'moving' step; drop one"),
    ("throughput", ["--max-tets", "100"], "--max-tets 100 leaves no mesh: the smallest has 144 tets"),
])
def test_an_option_quick_cannot_honour_is_refused_with_it(capsys, name, argv, match):
    """--quick would silently drop these (it runs no 'moving' step, not the whole grid, no mesh that small)."""
    exits_with_one_line(capsys, lambda: benchmark_module(name).main(["--quick"] + argv), match)


@pytest.mark.backend
def test_multilevel_quick_keeps_the_options_given(tmp_path):
    """--quick replaced sizes, moduli, states, cycles, sweeps and repeats even when given."""
    argv = ["--quick", "--no-progress", "--out", str(tmp_path), "--sizes", "1", "--moduli", "1e4", "--states", "rest",
            "--cycles", "2", "--max-sweeps", "3"]
    assert benchmark_module("multilevel").main(argv) == 0
    curves = rows(tmp_path / "multilevel.csv")
    assert {(r["tets"], r["E"], r["state"]) for r in curves} == {("60", "10000", "rest")}
    assert max(int(r["sweeps"]) for r in curves if r["method"] == "VBD") == 3
    assert max(int(r["count"]) for r in curves if r["method"] != "VBD") == 2


def test_summary_tables_say_not_reached_or_undefined_instead_of_nan():
    from benchmarks import multilevel, newton_speed, stability

    nan = float("nan")
    level = dict(E=1e6, tets=30720, N_c=42.2, state="rest", method="VBD", final_error=0.04, newton_seconds=nan,
                 reference="two-level 40 cycles", **{"count_to_0.01": 2000, "sweeps_to_0.01": 2000,
                                                    "seconds_to_0.01": 0.45, "count_to_0.0001": nan,
                                                    "sweeps_to_0.0001": nan, "seconds_to_0.0001": nan})
    text = multilevel.report([level])
    assert "| VBD | 2000 | 0.45 | not reached | not reached | not reached | 0.04 | - | two-level 40 cycles |" in text
    still = dict(resolution="coarse", tets=144, dt=1 / 60, E=1e4, nu=0.3, state="rest", finite=True, monotone=True,
                 recovers=True, error=nan, passed=True)
    text = stability.report([still])
    assert "| rest | 1 | 1 | 1 | 1 | - | - |" in text and "nan" not in text
    curve = dict(section="time_to_error", case="480 tets, rest", method="Newton-PCG (color_sweep)", final_error=0.1,
                 **{"t_1e-04": nan, "t_1e-06": nan, "newton_it_1e-04": nan, "cg_it_1e-04": nan})
    assert "| not reached | not reached | not reached | not reached | 0.1 |" in newton_speed.report([curve])


def test_throughput_fits_no_exponent_above_10k_tets_without_two_such_meshes():
    """--quick's meshes (144 and 1,152 tets) filled exponent_10k_up with the fit over all sizes."""
    from benchmarks.throughput import scaling_fits

    def measured(sizes):
        return [dict(tets=n, precision=p, threads=1, ms_per_iter=1e-4 * n) for n in sizes
                for p in ("float64", "float32")]

    small = scaling_fits(measured([144, 1152]), [1])
    assert [f["exponent_all"] for f in small] == pytest.approx([1.0, 1.0])
    assert [f["exponent_10k_up"] for f in small] == ["", ""]
    assert [f["exponent_10k_up"] for f in scaling_fits(measured([144, 12_000, 48_000]), [1])] == pytest.approx([1, 1])


@pytest.mark.parametrize("name", SCRIPTS + ("newton_speed", "multilevel", "inversion", "interactive_fps", "cuda",
                                           "before_after"))
def test_the_readme_says_what_each_benchmark_writes(name):
    module = benchmark_module(name)
    files = getattr(module, "OUTPUTS", None) or module.FILES
    with open(os.path.join(ROOT, "benchmarks", "README.md")) as fh:
        row = next(line for line in fh if line.startswith(f"| `.venv/bin/python -m benchmarks.{name}` |"))
    written = row.rstrip().rstrip("|").rsplit("|", 1)[1]
    assert sorted(f.strip(" `") for f in written.split(",")) == sorted(files)


@pytest.mark.backend
def test_newton_speed_quick_measures_only_the_installed_linear_solvers(tmp_path, capsys, monkeypatch):
    """The --quick run writes its CSVs, every method reaching x*. Without cvxopt and cholespy (the default
    install) there are no CHOLMOD or cholespy rows: they would be SuperLU's times under those names
    (DirectSolver falls back to it). The summary names them and says how to install them. A second run
    into the same folder replaces nothing without --overwrite. No timing is asserted."""
    monkeypatch.setitem(sys.modules, "cvxopt", None)         # not importable, installed or not
    monkeypatch.setitem(sys.modules, "cholespy", None)
    newton_speed = benchmark_module("newton_speed")
    assert newton_speed.main(["--quick", "--no-progress", "--out", str(tmp_path)]) == 0
    data = rows(tmp_path / "newton_speed.csv")
    assert {r["section"] for r in data} == {"converged step", "one iteration", "time_to_error"}
    assert all(float(r["final_error"]) < 1e-8 for r in data if r["section"] == "time_to_error"), data
    assert (tmp_path / "pcg.png").stat().st_size > 0
    measured = {r["method"] for r in data}
    curves = {r["method"] for r in rows(tmp_path / "pcg_curves.csv")}
    assert {"Newton (qdldl)", "Newton (superlu)"} <= measured and {"Newton (qdldl)", "Newton (superlu)"} <= curves
    assert not [m for m in measured | curves if "cholmod" in m or "cholespy" in m]
    skipped = ("Skipped, not installed: Newton (cholmod), Newton (cholespy); to measure them: "
               "pip install -r requirements-cholmod.txt.")
    assert skipped in capsys.readouterr().out and skipped in (tmp_path / "summary.md").read_text()
    written = (tmp_path / "newton_speed.csv").read_text()
    exits_with_one_line(capsys, lambda: newton_speed.main(["--quick", "--out", str(tmp_path)]),
                         "already exist; pass --overwrite")
    assert (tmp_path / "newton_speed.csv").read_text() == written


@pytest.mark.backend
def test_interactive_fps_quick_says_what_it_wrote(tmp_path, capsys):
    assert benchmark_module("interactive_fps").main(["--quick", "--no-progress", "--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == \
        f"wrote interactive_fps.csv, summary.md into {tmp_path}"
    from solver.newton.direct import DirectSolver, LinearSolver
    off, on = rows(tmp_path / "interactive_fps.csv")
    # the ghosts' solver is named, so that a quoted figure says which install it comes from (bars < 10^4 dofs)
    assert (off["ghosts"], off["ghost_solver"]) == ("off", "none")
    assert (on["ghosts"], on["ghost_solver"]) == \
        ("on", "cholmod" if DirectSolver.installed(LinearSolver.CHOLMOD) else "qdldl")
