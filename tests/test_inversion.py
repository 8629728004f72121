"""Inverted elements on a sliver mesh: the test case, VBD against the converged Newton trajectory,
and the benchmark that measures it (issue 11)."""
import csv
import warnings

import numpy as np
import pytest

import solver

pytestmark = pytest.mark.backend  # launches Taichi kernels: re-run on CUDA

MATERIAL = solver.Material(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
STEPS = 6


def _hung_sliver_box():
    mesh = solver.sliver_box_mesh()
    count = int(round(0.05 * mesh.n_vertices))
    fixed = np.zeros(mesh.n_vertices, bool)
    fixed[np.argsort(-mesh.vertices[:, 2], kind="stable")[:count]] = True
    return mesh, fixed


def _trajectories():
    """Inverted tets per step: plain VBD and VBD keeping orientation (50 iterations each) and converged
    Newton, each on its own trajectory."""
    mesh, fixed = _hung_sliver_box()
    vbd = {name: solver.Simulation(mesh, MATERIAL, dt=1 / 60, fixed=fixed, iterations=50, keep_orientation=keep)
           for name, keep in (("VBD", False), ("VBD keep_orientation", True))}
    newton = solver.Simulation(mesh, MATERIAL, dt=1 / 60, fixed=fixed, iterations=50)
    counts = {"VBD": [], "VBD keep_orientation": [], "Newton": []}
    for _ in range(STEPS):
        for name, sim in vbd.items():
            sim.step()
            counts[name].append(solver.inverted_count(mesh.vertices, mesh.tets, sim.positions))
            assert counts[name][-1] == sim.inverted_count()
        problem, x_n = newton.step_problem(), newton.positions
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            result = solver.newton_solve(problem, problem.y_with_constraints(), tolerance=1e-8)
        assert result.converged
        newton.set_positions(result.x)
        newton.set_velocities((result.x - x_n) / newton.dt)
        counts["Newton"].append(solver.inverted_count(mesh.vertices, mesh.tets, result.x))
    return counts


@pytest.fixture(scope="module")
def trajectories():
    return _trajectories()


def test_the_sliver_box_warns_on_load(tmp_path):
    mesh, _ = _hung_sliver_box()
    assert mesh.quality().n_slivers >= 50
    solver.save_mesh(mesh, tmp_path / "slivers.vtu")
    with pytest.warns(solver.MeshQualityWarning, match="slivers"):
        solver.load_mesh(tmp_path / "slivers.vtu")


def test_converged_newton_inverts_nothing_on_the_sliver_box(trajectories):
    assert trajectories["Newton"] == [0] * STEPS


def test_plain_vbd_tangles_the_sliver_box(trajectories):
    assert max(trajectories["VBD"]) > 0      # the failure keep_orientation removes


def test_vbd_keeping_orientation_inverts_no_more_tets_than_newton_on_the_sliver_box(trajectories):
    assert all(v <= n for v, n in zip(trajectories["VBD keep_orientation"], trajectories["Newton"]))


def test_inversion_benchmark_quick_writes_its_csv_and_refuses_to_overwrite(tmp_path, capsys):
    from benchmarks import inversion

    argv = ["--quick", "--no-progress", "--out", str(tmp_path)]
    assert inversion.main(argv) == 0
    with open(tmp_path / "inversion.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["method"] for r in rows} == {"VBD", "Newton"}
    assert len(rows) == 2 * 5
    newton = [r for r in rows if r["method"] == "Newton"]
    assert all(r["inverted"] == "0" and r["newton_converged"] == "True" for r in newton)
    assert all(float(r["min_det_F"]) > 0 for r in newton)
    assert (tmp_path / "inversion.png").stat().st_size > 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as again:
        inversion.main(argv)
    assert again.value.code == 2 and "--overwrite" in capsys.readouterr().err
