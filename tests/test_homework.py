"""The homework generator (`python -m demo homework`), the starter it writes and the autograder."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from demo import homework
from demo.__main__ import main
from demo.errors import DemoError

REPO = Path(__file__).resolve().parent.parent


def clean_env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VBD_GRADE_JSON")}
    env.update(extra)
    return env


def run(args, cwd, timeout=300, **env):
    return subprocess.run([sys.executable, *args], cwd=cwd, env=clean_env(**env), capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def starter(tmp_path_factory):
    out = tmp_path_factory.mktemp("starter") / "hw"
    homework.generate(out, quiet=True)
    return out


def starter_py_files(starter):
    return sorted(p for p in starter.rglob("*.py") if "grading" not in p.parts)


def test_every_task_has_a_region_and_the_points_add_up():
    regions = homework.all_regions(REPO)
    assert {r.task.id for r in regions} == {t.id for t in homework.TASKS}
    assert {"force_hessian", "coloring", "vbd_sweep", "chebyshev"} <= {t.id for t in homework.TASKS}
    assert sum(t.points for t in homework.TASKS) == 100
    for task in homework.TASKS:
        assert (REPO / task.chapter).exists(), task.chapter


def test_starter_layout_and_readme(starter):
    assert (starter / "solver" / "__init__.py").exists() and (starter / "demo" / "__main__.py").exists()
    assert (starter / "grading" / "conftest.py").exists() and (starter / "lecture_notes").is_dir()
    for absent in (".git", ".venv", "tests", "homework", "vbd_taichi.egg-info"):
        assert not (starter / absent).exists(), absent
    assert "testpaths = grading" in (starter / "pytest.ini").read_text()
    readme = (starter / "README.md").read_text()
    for task in homework.TASKS:
        assert f"`{task.id}`" in readme and f"| {task.points} |" in readme and task.chapter in readme
    assert "python -m pytest" in readme and "{{" not in readme


def test_regions_become_todo_raises(starter):
    texts = {p.relative_to(starter).as_posix(): p.read_text() for p in starter_py_files(starter)}
    for region in homework.all_regions(REPO):
        message = homework.todo_message(region.task, region.function)
        assert f'raise NotImplementedError("{message}")' in texts[region.path.as_posix()]
        assert message.startswith(f"TODO: {region.task.id}: ") and "see lecture_notes/" in message
    for name, text in texts.items():
        lines = text.splitlines()
        for number in homework._comment_lines(text):
            assert not re.match(r"\s*# (BEGIN|END) SOLUTION", lines[number - 1]), f"marker left in {name}:{number}"


def test_no_solution_line_survives(starter):
    """Every line of a solution region appears in the starter no more often than it does outside the
    regions in the solution (lines like `i = self.color_order[k]` also occur elsewhere)."""
    by_file = {}
    for region in homework.all_regions(REPO):
        by_file.setdefault(region.path, []).append(region)
    for path, regions in by_file.items():
        solution = (REPO / path).read_text().splitlines()
        inside = {n for r in regions for n in range(r.start, r.end + 1)}
        outside = [line.strip() for n, line in enumerate(solution, start=1) if n not in inside]
        starter_lines = [line.strip() for line in (starter / path).read_text().splitlines()]
        for region in regions:
            for line in region.lines:
                code = line.strip()
                if not code or code.startswith("#"):
                    continue
                assert starter_lines.count(code) <= outside.count(code), \
                    f"solution line survives in the starter {path}: {code}"


def test_starter_imports_cleanly(starter):
    result = run(["-c", "import solver, solver.simulation, demo, demo.scenes, demo.runner; print('ok')"], starter)
    assert result.returncode == 0 and "ok" in result.stdout, result.stderr


def test_demo_in_the_starter_stops_with_one_line(starter):
    result = run(["-m", "demo"], starter)
    output = [line for line in (result.stdout + result.stderr).splitlines()
              if not line.startswith(("[Taichi]", "[Quadrants]"))]
    assert result.returncode != 0
    assert "Traceback" not in result.stdout + result.stderr, result.stderr
    assert len(output) == 1, output
    assert output[0].startswith("not yet implemented: force_hessian: vertex_force_hessian"), output


def test_graded_tests_fail_on_the_starter_with_their_todo(starter, tmp_path):
    score = tmp_path / "score.json"
    result = run(["-m", "pytest", "-q", "-p", "no:cacheprovider"], starter, VBD_GRADE_JSON=str(score))
    assert result.returncode != 0
    report = json.loads(score.read_text())
    assert report["earned"] == 0 and report["total"] == 100
    assert set(report["tasks"]) == {t.id for t in homework.TASKS}
    assert len(report["tests"]) >= 16
    for nodeid, test in report["tests"].items():
        assert not test["passed"] and test["reason"].startswith(f"TODO: {test['task']}: "), (nodeid, test)
    assert "VBD homework score" in result.stdout and "not implemented: force_hessian" in result.stdout


@pytest.mark.slow
def test_graded_tests_pass_on_the_solution(tmp_path):
    score = tmp_path / "score.json"
    result = run(["-m", "pytest", "-q", "-p", "no:cacheprovider", "homework/grading"], REPO,
                 VBD_GRADE_JSON=str(score))
    assert result.returncode == 0, result.stdout[-3000:]
    report = json.loads(score.read_text())
    assert report["earned"] == report["total"] == 100
    assert all(t["passed"] for t in report["tests"].values())


def test_existing_folder_is_refused_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "hw"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["homework", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is not empty; pass --overwrite" in err, err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert main(["homework", "--out", str(out), "--overwrite"]) == 0
    assert (out / "notes.txt").read_text() == "mine"          # a folder we did not write is never emptied
    assert (out / "solver" / "material.py").exists()
    (out / "stale.py").write_text("")
    assert main(["homework", "--out", str(out), "--overwrite"]) == 0
    assert not (out / "stale.py").exists()                    # an earlier starter is replaced cleanly


def test_refuses_to_write_into_the_project_itself(capsys):
    assert main(["homework", "--out", str(REPO)]) == 2
    assert "contains the project itself" in capsys.readouterr().err


def test_a_starter_cannot_make_a_starter(starter, tmp_path):
    with pytest.raises(DemoError, match="no solution region for task"):
        homework.generate(tmp_path / "again", root=starter, quiet=True)


@pytest.mark.parametrize("source, match", [
    ("def f():\n    # BEGIN SOLUTION\n    x = 1\n    # END SOLUTION\n", "needs task=ID"),
    ("def f():\n    # BEGIN SOLUTION task=nope\n    x = 1\n    # END SOLUTION\n", "got 'nope'"),
    ("def f():\n    # BEGIN SOLUTION task=coloring\n    x = 1\n", "never closed"),
    ("def f():\n    x = 1\n    # END SOLUTION\n", "without BEGIN"),
    ("def f():\n    # BEGIN SOLUTION task=coloring\n    x = 1\n    # END SOLUTION\n", "does not list"),
])
def test_malformed_regions_are_reported(source, match):
    with pytest.raises(DemoError, match=match):
        homework.find_regions(Path("solver/coloring.py"), source)


def test_markers_in_strings_are_not_regions():
    source = 'def f():\n    """\n    # BEGIN SOLUTION task=coloring\n    """\n    return 1\n'
    assert homework.find_regions(Path("solver/coloring.py"), source) == []


def test_require_implemented_reads_the_todo_line(tmp_path):
    import importlib.util

    from solver.todo import require_implemented

    path = tmp_path / "stub_module.py"
    path.write_text("def stub():\n    raise NotImplementedError(\"TODO: coloring: x; see y\")\n\n\n"
                    "def done():\n    return 1\n")
    spec = importlib.util.spec_from_file_location("stub_module", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    require_implemented(module.done)
    with pytest.raises(NotImplementedError, match="^TODO: coloring: x; see y$"):
        require_implemented(module.done, module.stub)


def test_starter_notes_quote_the_starter_code(starter):
    from demo import figures

    chapter = (starter / "lecture_notes" / "03-coordinate-descent.md").read_text()
    assert 'raise NotImplementedError("TODO: force_hessian: ' in chapter
    assert figures.stale({}, starter / "lecture_notes", root=starter) == [] or all(
        "excerpt" not in p for p in figures.stale({}, starter / "lecture_notes", root=starter))
    # no distinctive solution line (one that occurs nowhere outside the regions) is anywhere in the starter
    regions = homework.all_regions(REPO)
    inside = {}
    for r in regions:
        inside.setdefault(r.path, set()).update(range(r.start, r.end + 1))
    outside = set()
    for path, numbers in inside.items():
        outside |= {line.strip() for n, line in enumerate((REPO / path).read_text().splitlines(), start=1)
                    if n not in numbers}
    distinctive = {line.strip() for r in regions for line in r.lines
                   if len(line.strip()) > 12 and not line.strip().startswith("#")} - outside
    assert len(distinctive) > 10
    for path in starter.rglob("*"):
        if path.suffix in (".py", ".md") and path.is_file():
            lines = {line.strip() for line in path.read_text().splitlines()}
            assert not (lines & distinctive), (path, lines & distinctive)
