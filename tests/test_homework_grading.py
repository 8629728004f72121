"""The homework autograder (`python -m demo homework grade`): planted bugs, classes graded in parallel,
gamed starters. Split from tests/test_homework.py so that --dist loadfile runs the graded subprocesses
on one worker and the generator's tests on the other."""
import json
import shutil
from pathlib import Path

import pytest

from demo import homework
from tests.homework_checks import REPO, as_solution, run, starter  # noqa: F401 (starter: a fixture)

# the graded runs are subprocesses, but the grader builds a starter (kernels) in this process: re-run on CUDA
pytestmark = pytest.mark.backend


@pytest.fixture(scope="module")
def grader(tmp_path_factory):
    return homework.Grader(tmp_path_factory.mktemp("grader"), jobs=2)


def earned(grades):
    return {g.task: g.earned for g in grades}


@pytest.mark.slow
def test_the_solution_scores_100_and_the_untouched_starter_0(grader, starter, tmp_path):
    full = earned(grader.grade(as_solution(starter, tmp_path / "solution")))
    assert full == {t.id: t.points for t in homework.TASKS}, full
    zero = grader.grade(starter)
    assert earned(zero) == {t.id: 0 for t in homework.TASKS}
    assert all(g.reason.startswith(f"TODO: {g.task}: ") for g in zero), zero


# (task, file, solution text, planted bug, words the first failure must contain)
BUGS = [
    ("force_hessian", "solver/physics/material.py", "f = -vol * (mu * Fm", "f = -(mu * Fm", "f_i"),
    ("force_hessian", "solver/physics/material.py", "lam * w.outer_product(w)", "w.outer_product(w)", "H_i"),
    ("coloring", "solver/mesh/coloring.py", "used |= ti.u64(1) << ti.u64(c)", "used |= ti.u64(0)", "share a colour"),
    ("vbd_sweep", "solver/vbd/vertex_solve.py", "f = -inertia_gradient(m_h2, x_i, state[Y, i])",
     "f = ti.Vector.zero(dtype, 3)",
     "inertia term of f_i"),
    ("vbd_sweep", "solver/vbd/vertex_solve.py", "H = inertia_block(m_h2)", "H = ti.Matrix.zero(dtype, 3, 3)",
     "inertia term of H_i"),
    ("vbd_sweep", "solver/vbd/vertex_solve.py", "    f += f_el\n", "    f += 0.5 * f_el\n", "elasticity term of f_i"),
    ("vbd_sweep", "solver/vbd/vertex_solve.py", "    H += H_el\n", "    H += 0.5 * H_el\n", "elasticity term of H_i"),
    ("vbd_sweep", "solver/vbd/vertex_solve.py", "dx = ti.cast(H_inv @ f, dtype)",
     "dx = ti.cast(0.5 * H_inv @ f, dtype)", "solved last"),
    ("chebyshev", "solver/vbd/chebyshev.py", "return 2.0 / (2.0 - rho * rho)", "return 2.0 / (2.0 - rho)", "assert"),
    ("chebyshev", "solver/vbd/chebyshev.py", "state[X_PREV2, i] = state[X_PREV, i]", "state[X_PREV2, i] = x_accel",
     "assert"),
    ("analysis", "exercises/analysis.py", "np.kron(np.eye(3), np.reshape(np.asarray(m, dtype=float), (3, 1)))",
     "np.kron(np.reshape(np.asarray(m, dtype=float), (3, 1)), np.eye(3))", "dF_dx(m) is not"),
    ("analysis", "exercises/analysis.py", "x[free] + omega * np.linalg.solve(", "x[free] + np.linalg.solve(",
     "under-relaxed Jacobi"),
]


def plant(submission: Path, file: str, right: str, wrong: str) -> Path:
    """The submission with `right` (found exactly once in `file`) replaced by the bug `wrong`."""
    text = (submission / file).read_text()
    assert text.count(right) == 1, f"the solution no longer contains {right!r}: update BUGS"
    (submission / file).write_text(text.replace(right, wrong))
    return submission


def assert_costs_only_its_task(grades, task, words):
    """The bug of `task` loses points there only (in every other task graded), and the first failure names
    it in one short line."""
    grades = {g.task: g for g in grades}
    assert task in grades and len(grades) > 1, grades
    for other in homework.TASKS:
        if other.id != task and other.id in grades:
            assert grades[other.id].earned == other.points, (task, other.id, grades[other.id])
    assert grades[task].earned < grades[task].points and words in grades[task].reason, grades[task]
    assert "\n" not in grades[task].reason and len(grades[task].reason) <= 160


def test_a_planted_bug_costs_only_its_task(grader, starter, tmp_path):
    """One bug (the elasticity term of f_i halved) loses points in its own task only, and the first failure
    names what is wrong. Graded here with one other task, Chebyshev's, whose tests run the sweep: its tree
    has the solution's sweep, so it keeps its points (every task, for every bug: the slow class test)."""
    task, file, right, wrong, words = BUGS[5]
    submission = plant(as_solution(starter, tmp_path / "bugged"), file, right, wrong)
    assert_costs_only_its_task(grader.grade(submission, tasks=[task, "chebyshev"]), task, words)


@pytest.mark.slow
def test_a_submission_that_never_returns_is_stopped_at_the_timeout_and_scores_0(starter, tmp_path):
    """An endless wait in one task's function (a student's infinite loop) stops that task's graded run at
    the grader's timeout, with 0 points and the reason, instead of holding the class up; the other task
    graded beside it keeps its points."""
    submission = plant(as_solution(starter, tmp_path / "looping"), "exercises/analysis.py",
                       "x[free] + omega * np.linalg.solve(", "__import__('time').sleep(3600) or x[free] + omega * "
                       "np.linalg.solve(")
    timeout = 40
    grades = {g.task: g for g in homework.Grader(tmp_path / "grader", jobs=2, timeout=timeout).grade(
        submission, tasks=["analysis", "coloring"])}
    assert grades["analysis"].earned == 0 and f"ran past {timeout} s" in grades["analysis"].reason
    assert grades["coloring"].earned == grades["coloring"].points


@pytest.mark.slow
def test_every_planted_bug_costs_only_its_task(grader, starter, tmp_path):
    """Each bug (one per task, and one per term of f_i and H_i) in its own submission, the class graded
    in parallel: each loses points in its own task only, and its first failure names what is wrong."""
    klass = {f"bug{n}": plant(as_solution(starter, tmp_path / f"bug{n}"), file, right, wrong)
             for n, (_, file, right, wrong, _) in enumerate(BUGS)}
    book = grader.grade_all(klass)
    for n, (task, _, _, _, words) in enumerate(BUGS):
        assert_costs_only_its_task(book[f"bug{n}"], task, words)


def test_a_class_graded_in_parallel_runs_each_distinct_task_once_and_reports_in_order(grader, starter, tmp_path,
                                                                                      monkeypatch):
    """grade_all with 3 jobs: every (task, spliced files) is run once however many students share it, the
    runs finish in any order, and each student is reported in class order with the grades a serial run
    gives. The graded runs are stood in for by a function of the spliced text (the real ones are tested above
    and in the slow class test)."""
    import copy
    import random
    import threading
    import time

    klass = {"ann": as_solution(starter, tmp_path / "ann"), "bob": starter,
             "cy": as_solution(starter, tmp_path / "cy"), "dee": as_solution(starter, tmp_path / "dee")}
    text = (klass["cy"] / BUGS[0][1]).read_text()
    (klass["cy"] / BUGS[0][1]).write_text(text.replace(BUGS[0][2], BUGS[0][3]))
    (klass["dee"] / BUGS[0][1]).unlink()                       # force_hessian's file: gone
    (klass["dee"] / BUGS[2][1]).write_text("def _greedy(:\n")   # coloring's: does not parse
    runs, lock, rng = [], threading.Lock(), random.Random(0)

    def fake_run(self, task, spliced, run):
        time.sleep(rng.uniform(0.0, 0.02))
        with lock:
            runs.append((task.id, tuple(sorted(spliced.items()))))
        points = task.points * ("TODO" not in "".join(spliced.values())) * (BUGS[0][3] not in "".join(spliced.values()))
        return homework.TaskGrade(task.id, float(points), task.points, 1, 1, f"run {run}")

    monkeypatch.setattr(homework.Grader, "_run", fake_run)
    books = {}
    for jobs in (1, 3):
        fresh = copy.copy(grader)
        fresh._graded, fresh.jobs, runs[:] = {}, jobs, []
        order = []
        books[jobs] = fresh.grade_all(klass, done=lambda name, grades: order.append(name))
        assert order == ["ann", "bob", "cy", "dee"]
        assert len(runs) == len(set(runs)) == 2 * len(homework.TASKS) + 1      # cy and dee share the rest with ann
    earned = {jobs: {name: [g.earned for g in grades] for name, grades in book.items()} for jobs, book in books.items()}
    assert earned[1] == earned[3]
    assert earned[3]["ann"] == [t.points for t in homework.TASKS] and sum(earned[3]["bob"]) == 0
    assert earned[3]["cy"] == [0.0 if t.id == BUGS[0][0] else t.points for t in homework.TASKS]
    assert earned[3]["dee"] == [0.0 if t.id in (BUGS[0][0], BUGS[2][0]) else t.points for t in homework.TASKS]
    reasons = {g.task: g.reason for g in books[3]["dee"]}
    assert reasons[BUGS[0][0]] == f"{BUGS[0][1]} is missing"
    assert reasons[BUGS[2][0]].startswith(f"{BUGS[2][1]} does not parse (line 1")


def test_stopping_a_class_grading_starts_no_further_run(grader, starter, tmp_path, monkeypatch):
    """Ctrl-C while a class is graded (here raised as the first student is reported, one job) cancels the
    runs not yet started instead of working through the queue."""
    import copy
    import time

    started = []

    def fake_run(self, task, spliced, run):
        started.append(run)
        time.sleep(0.05)
        return homework.TaskGrade(task.id, 0.0, task.points, 0, 1, "stand-in")

    def interrupt(name, grades):
        raise KeyboardInterrupt

    monkeypatch.setattr(homework.Grader, "_run", fake_run)
    fresh = copy.copy(grader)
    fresh._graded, fresh.jobs = {}, 1
    with pytest.raises(KeyboardInterrupt):
        fresh.grade_all({"ann": as_solution(starter, tmp_path / "ann"), "bob": starter}, done=interrupt)
    assert len(homework.TASKS) <= len(started) <= len(homework.TASKS) + 1


def game(starter: Path, folder: Path) -> Path:
    """The starter with every task still a TODO, gamed: a root conftest.py that turns every test into a
    no-op, a gutted grading/ (gradelib's require a no-op, a task's tests replaced), an edited pytest.ini and
    a task file whose other functions lie (the energy the tests check against is zero)."""
    shutil.copytree(starter, folder)
    (folder / "conftest.py").write_text(
        "def pytest_collection_modifyitems(items):\n"
        "    for item in items:\n"
        "        item.runtest = lambda: None\n")
    (folder / "grading" / "gradelib.py").write_text(
        (folder / "grading" / "gradelib.py").read_text() + "\n\ndef require(task_id):\n    return None\n")
    (folder / "grading" / "test_2_coloring.py").write_text(
        "import pytest\n\npytestmark = pytest.mark.task('coloring')\n\n\ndef test_ok():\n    pass\n")
    (folder / "pytest.ini").write_text((folder / "pytest.ini").read_text() + "addopts = -p no:warnings\n")
    material = folder / "solver" / "physics" / "material.py"
    material.write_text(material.read_text() + "\n\ndef psi_np(F, mu, lam):\n    return 0 * F[..., 0, 0]\n")
    return folder


def test_a_gamed_starter_scores_0_and_a_class_gets_a_gradebook(starter, tmp_path, capsys):
    """The gaming works on the student's own run (100/100 with every task a TODO) and gets nothing from
    the grader; a folder of submissions is graded as a class, the gradebook written as JSON. Graded on
    the two tasks the gaming edits (colouring: its tests replaced; force_hessian: the energy it is checked
    against zeroed); the slow class tests grade every task. The command runs in this process (its graded
    runs in their own), so that it reuses the references the starter was written with."""
    from demo.__main__ import main

    klass = tmp_path / "class"
    klass.mkdir()
    gamed = game(starter, klass / "gamed")
    shutil.copytree(starter, klass / "untouched")
    score = tmp_path / "own.json"
    run(["-m", "pytest", "-q", "-p", "no:cacheprovider"], gamed, VBD_GRADE_JSON=str(score))
    assert json.loads(score.read_text())["earned"] == 100      # the student's own run is fooled
    book = tmp_path / "book.json"
    capsys.readouterr()
    assert main(["homework", "grade", str(klass), "--json", str(book), "--task", "coloring",
                 "--task", "force_hessian"]) == 0
    out = capsys.readouterr().out
    lines = out.strip().splitlines()
    assert lines[-1] == "total: 0/40" and "== gamed" in lines and "== untouched" in lines, out
    assert lines.count("total: 0/40") == 2
    gradebook = json.loads(book.read_text())
    assert set(gradebook) == {"gamed", "untouched"}
    assert all(entry["earned"] == 0 and entry["total"] == 40 for entry in gradebook.values()), gradebook
