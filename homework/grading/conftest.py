"""Autograder set-up: import the project this folder sits in, and score the graded tests per task.

Every graded test carries ``pytest.mark.task("<id>")``. A task earns its points times the fraction of
its tests that pass; the table is printed at the end of the run, and written as JSON to the file
named by the environment variable ``VBD_GRADE_JSON`` when it is set.
"""
import json
import os
from pathlib import Path

import pytest


def _project_root() -> Path:
    here = Path(__file__).resolve().parent
    for folder in (here, *here.parents):
        if (folder / "solver" / "__init__.py").exists():
            return folder
    raise RuntimeError(f"no solver/ package above {here}")


ROOT = _project_root()
os.environ["VBD_CACHE_DIR"] = ""       # no colouring cache: always run the colouring under test

from demo.homework import TASKS  # noqa: E402

_results = {}   # nodeid -> (task, passed, first line of the failure)


def pytest_configure(config):
    config.addinivalue_line("markers", "task(id): the homework task a graded test belongs to")


def pytest_sessionstart(session):
    """Grade this copy of the project, whatever else is installed: pytest.ini's ``pythonpath = .``
    puts it first on the import path; stop with one line where something else came first."""
    import demo
    import solver

    for package in (solver, demo):
        found = Path(package.__file__).resolve().parent.parent
        if found != ROOT:
            pytest.exit(f"the grader imported {package.__name__} from {found}, not from {ROOT}; run pytest "
                        f"inside {ROOT} (its pytest.ini puts that folder first on the import path)", returncode=4)


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    import solver

    solver.ensure_taichi("cpu")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    marker = item.get_closest_marker("task")
    if marker is None:
        return
    if report.skipped or not (report.when == "call" or (report.when == "setup" and report.failed)):
        return
    reason = _failure_line(report) if report.failed else ""
    _results[item.nodeid] = (marker.args[0], report.passed, reason)


def _failure_line(report) -> str:
    """One line saying why a graded test failed: the TODO message, else the first line of the error."""
    todo = [line for line in str(report.longrepr).splitlines() if "NotImplementedError: TODO:" in line]
    if todo:
        return todo[0].split("NotImplementedError: ", 1)[1]
    crash = getattr(report.longrepr, "reprcrash", None)
    line = crash.message.splitlines()[0] if crash is not None and crash.message else "failed"
    line = line.removeprefix("AssertionError: ")
    return line if len(line) <= 160 else line[:157] + "..."


def scores():
    """{task id: dict(points, earned, passed, total, reason)} for the tests that ran."""
    table = {}
    for task in TASKS:
        runs = [(passed, reason) for t, passed, reason in _results.values() if t == task.id]
        if not runs:
            continue
        passed = sum(1 for ok, _ in runs if ok)
        reasons = [r for ok, r in runs if not ok]
        todo = [r for r in reasons if r.startswith("TODO:")]
        table[task.id] = {"points": task.points, "earned": round(task.points * passed / len(runs), 2),
                          "passed": passed, "total": len(runs), "todo": todo[0] if todo else "",
                          "reason": reasons[0] if reasons else ""}
    return table


def pytest_terminal_summary(terminalreporter):
    table = scores()
    if not table:
        return
    write = terminalreporter.write_line
    terminalreporter.section("VBD homework score")
    for task_id, row in table.items():
        todo = f"   not implemented: {row['todo'][6:]}" if row["todo"] and row["passed"] == 0 else ""
        write(f"{task_id:15s} {row['earned']:6.1f} / {row['points']:3d}   "
              f"{row['passed']}/{row['total']} tests passed{todo}")
    earned = sum(r["earned"] for r in table.values())
    total = sum(r["points"] for r in table.values())
    write(f"{'total':15s} {earned:6.1f} / {total:3d}")
    path = os.environ.get("VBD_GRADE_JSON")
    if path:
        tests = {nodeid: {"task": task, "passed": passed, "reason": reason}
                 for nodeid, (task, passed, reason) in _results.items()}
        Path(path).write_text(json.dumps({"tasks": table, "earned": earned, "total": total, "tests": tests},
                                         indent=2) + "\n")
