"""The homework generator (`python -m demo homework`), the starter it writes and the autograder's
checks of its input; the graded runs are in tests/test_homework_grading.py."""
import json
import re
from pathlib import Path

import pytest

from demo import homework
from demo.__main__ import main
from demo.errors import DemoError
from tests.homework_checks import REPO, as_solution, run, starter  # noqa: F401 (starter: a fixture)

# generating a starter runs the solution's reference steps (kernels): re-run on CUDA too
pytestmark = pytest.mark.backend


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


# What a chapter must say where a task function's name is not in it: the topic the function is cited for.
TOPICS = {"dF_dx": "affine", "hessian_eigenvalues": "positive definite", "iterations_needed": "N_c",
          "rho_residuals": "spectral radius", "best_rho": "spectral radius", "jacobi_against_coloring": "under-relax"}


def test_every_chapter_a_todo_or_task_names_covers_it(starter):
    """Each TODO (its raise and its comment in the starter) names one chapter, which holds the function's
    name or its topic; every chapter and quoted section a task's README text names exists."""
    notes = REPO / "lecture_notes"
    for region in homework.all_regions(REPO):
        short = region.function.rsplit(".", 1)[-1]
        chapter = region.task.chapter_of(region.function)
        message = homework.todo_message(region.task, region.function)
        cited = re.findall(r"lecture_notes/\S+?\.md", message)
        assert cited == [chapter], (short, cited)
        text = (REPO / chapter).read_text()
        covered = re.search(rf"\b{re.escape(short)}\b", text) is not None or TOPICS[short] in text
        assert covered, f"{chapter} has neither {short} nor its topic {TOPICS.get(short)!r}"
        lines = (starter / region.path).read_text().splitlines()
        at = next(n for n, line in enumerate(lines) if message in line)
        first = at
        while lines[first - 1].lstrip().startswith("#"):
            first -= 1
        comment = " ".join(line.strip().lstrip("# ") for line in lines[first:at])
        assert f"see {chapter}." in comment, (short, comment)
    for task in homework.TASKS:
        for number, section in re.findall(r'chapter (\d+)(?:, "([^"]+)")?', task.details):
            (path,) = notes.glob(f"{int(number):02d}-*.md")
            headed = not section or re.search(rf"^#+ {re.escape(section)}$", path.read_text(), flags=re.M)
            assert headed, f"task {task.id} quotes a section {section!r} that {path.name} does not have"
        assert all((REPO / chapter).is_file() for chapter in task.all_chapters()), task.id


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


# ---------------------------------------------------------------------------------------------
# No file of the starter carries a task's answer in any form
# ---------------------------------------------------------------------------------------------
_PREFIX = re.compile(r"\b(?:self\.sim\.|self\.|sim\.|np\.linalg\.|np\.|ti\.math\.|ti\.)")
_BROADCAST = re.compile(r"\[(?:\s*(?::|None|\.\.\.)\s*,?)+\]")     # x[:, None], H[..., None, None]
_COLUMN = re.compile(r"\b\w+\[[\"'](\w+)[\"']\]")                   # col["q"] -> q
_INDEX = re.compile(r"\[[a-z]\]")                                   # y[i], y[v] -> y[_]
_ASSIGN = re.compile(r"^[\w\[\]\.,\s]+?(?:[-+*/@|&^]|<<|>>)?=(?!=)(?P<rhs>.*)$")


def skeleton(line: str) -> str:
    """A code line reduced to what survives a rewrite in Taichi or vectorised numpy: no comment, no
    `self.`/`np.`/`ti.` prefixes, no broadcasting indices, one index name, the right-hand side of an
    assignment only, no spaces or parentheses."""
    code = line.split("#", 1)[0]
    code = _INDEX.sub("[_]", _BROADCAST.sub("", _PREFIX.sub("", _COLUMN.sub(r"\1", code))))
    match = _ASSIGN.match(code.strip())
    if match:
        code = match["rhs"]
    return re.sub(r"[\s()]", "", code)


def answer_skeletons(root=REPO, min_length=10):
    """{task id: skeletons of its solution lines that occur in no line outside the solution regions}."""
    regions = homework.all_regions(root)
    inside = {}
    for r in regions:
        inside.setdefault(r.path, set()).update(range(r.start, r.end + 1))
    common = set()
    for path, numbers in inside.items():
        common |= {skeleton(line) for n, line in enumerate((root / path).read_text().splitlines(), start=1)
                   if n not in numbers}
    found = {}
    for r in regions:
        for line in r.lines:
            sk = skeleton(line)
            if len(sk) >= min_length and not any(sk in other for other in common):
                found.setdefault(r.task.id, set()).add(sk)
    return found


def leaks(text: str, answers: dict) -> set:
    """(task, skeleton) pairs of `answers` that some line of `text` contains."""
    lines = {skeleton(line) for line in text.splitlines()}
    return {(task, sk) for task, sks in answers.items() for sk in sks if any(sk in line for line in lines)}


def text_files(folder: Path):
    for path in sorted(folder.rglob("*")):
        if path.is_file() and path.stat().st_size < 4_000_000:
            try:
                yield path, path.read_text(encoding="utf-8")
            except UnicodeDecodeError:
                continue        # images and other binary files


def test_every_task_has_distinctive_answer_lines():
    answers = answer_skeletons()
    assert set(answers) == {t.id for t in homework.TASKS}
    assert all(len(sks) >= 2 for sks in answers.values()), answers


def test_leak_scanner_finds_each_answer_rewritten():
    """The scanner finds every task's solution lines re-indented inside other code, and the numpy twins
    that benchmarks/baselines.py held (the reason benchmarks/ is not in the starter)."""
    answers = answer_skeletons()
    for task in homework.TASKS:
        lines = [line.strip() for r in homework.all_regions(REPO) if r.task is task for line in r.lines]
        text = "class Other:\n    def method(self):\n" + "\n".join("        " + line for line in lines)
        assert {t for t, _ in leaks(text, answers)} == {task.id}, task.id
    numpy_vbd = (
        "        f_e = -vol[:, None] * (mu * Fm + (lam * (J - alpha))[:, None] * w)\n"
        "        m_h2 = mass[v] / (h * h)\n"
        "        x[v] += np.linalg.solve(H, f[:, :, None])[:, :, 0]\n")
    assert {t for t, _ in leaks(numpy_vbd, answers)} >= {"force_hessian", "vbd_sweep"}
    jacobi = ("            d = ti.Vector.zero(self.sim.dtype, 3)\n"
              "            H_inv = H.inverse()\n"
              "            if H.norm() * H_inv.norm() < max_condition(dtype):\n"
              "                d = ti.cast(H_inv @ f, dtype)\n")
    assert "vbd_sweep" in {t for t, _ in leaks(jacobi, answers)}
    assert not leaks("def unrelated(a, b):\n    return a + b\n", answers)


def test_no_file_of_the_starter_carries_an_answer(starter):
    """Every text file of the generated starter (code, notes, READMEs, grading, data) is scanned for every
    task's distinctive solution lines, in Taichi or numpy form."""
    answers = answer_skeletons()
    found = {}
    for path, text in text_files(starter):
        hits = leaks(text, answers)
        if hits:
            found[path.relative_to(starter).as_posix()] = sorted(hits)
    assert not found, found
    for path, why in homework.ANSWER_PATHS.items():
        assert not (starter / path).exists(), path
        assert f"`{path.as_posix()}/`" in (starter / "README.md").read_text()


def test_student_readme_runs_everything_with_the_venv_python(starter):
    """The README creates .venv; every command after that must use its python (a bare `python` has no Taichi)."""
    readme = (starter / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", readme, flags=re.S)
    commands = [line.split("#")[0].strip() for block in blocks for line in block.splitlines()]
    commands = [c for c in commands if c]
    assert any(c.startswith("python3 -m venv .venv") for c in commands)
    runs = [c for c in commands if re.search(r"(^|\s|&&\s*)(\S*/)?python3?\s", c) and "-m venv" not in c]
    assert runs and all(c.startswith(".venv/bin/python ") for c in runs), runs
    assert ".venv/bin/python -m pytest" in readme and ".venv/bin/python -m demo render colouring" in readme
    assert re.search(r"`?python -m (pytest|demo)", readme.replace(".venv/bin/python", "")) is None
    assert "dpsi_dF_np" in readme and "d2psi_dF2_np" in readme      # what stays on purpose, and why


def implement(starter: Path, task_id: str, extra_line: str = ""):
    """Put `task_id`'s solution regions back into a starter (plus `extra_line` at their top), as a student would."""
    for region in homework.all_regions(REPO):
        if region.task.id != task_id:
            continue
        path = starter / region.path
        lines = path.read_text().splitlines(keepends=True)
        raise_line = f'raise NotImplementedError("{homework.todo_message(region.task, region.function)}")'
        at = next(n for n, line in enumerate(lines) if line.strip() == raise_line)
        first = at
        while lines[first - 1].strip().startswith("#"):
            first -= 1
        indent = lines[at][:len(lines[at]) - len(lines[at].lstrip())]
        body = ([indent + extra_line + "\n"] if extra_line else []) + [line + "\n" for line in region.lines]
        path.write_text("".join(lines[:first] + body + lines[at + 1:]))


def test_coloring_picture_needs_only_the_coloring_task(tmp_path):
    """`demo render colouring` in a starter: stops with the colouring TODO, renders once task 2 alone is
    done, and computes the colouring with the student's code even where the solution cached one."""
    import numpy as np

    import solver
    from demo import scenes
    from solver.mesh import coloring

    out = tmp_path / "hw"
    homework.generate(out, quiet=True)
    cache = tmp_path / "cache"
    cache.mkdir()
    mesh = scenes.get("colouring").panels[0].mesh.build()
    solution_key = f"{mesh.topology_key()}-{solver.VertexOrder.NATURAL.value}-{coloring._greedy_digest()}"
    np.save(cache / f"colors-{solution_key}.npy", np.arange(mesh.n_vertices, dtype=np.int32))  # valid, not greedy
    command = ["-m", "demo", "render", "colouring", "--out", str(tmp_path / "pic"), "--size", "160x90",
               "--video", "none"]
    before = run(command, out, VBD_CACHE_DIR=str(cache))
    assert before.returncode == 3 and "not yet implemented: coloring: _greedy" in before.stderr, before.stderr
    implement(out, "coloring", extra_line="# my colouring")
    after = run(command, out, VBD_CACHE_DIR=str(cache))
    assert after.returncode == 0, after.stderr[-2000:]
    assert (tmp_path / "pic" / "frame_0000.png").exists()
    assert "wrote 1 frame to" in after.stdout, after.stdout
    written = sorted(p.name for p in cache.glob("colors-*.npy"))
    assert len(written) == 2 and f"colors-{solution_key}.npy" in written, written   # its own, not the solution's


def test_starter_imports_cleanly(starter):
    result = run(["-c", "import solver, solver.vbd.simulation, demo, demo.scenes, demo.runner; print('ok')"], starter)
    assert result.returncode == 0 and "ok" in result.stdout, result.stderr


def test_demo_in_the_starter_stops_with_one_line(starter):
    result = run(["-m", "demo"], starter)
    output = [line for line in (result.stdout + result.stderr).splitlines()
              if not line.startswith(("[Taichi]", "[Quadrants]"))]
    assert result.returncode != 0
    assert "Traceback" not in result.stdout + result.stderr, result.stderr
    assert len(output) == 1, output
    assert output[0].startswith("not yet implemented: force_hessian: vertex_force_hessian"), output


def test_demo_help_in_the_starter_lists_only_its_commands(starter):
    """The starter has no demo/figures.py: `python -m demo --help` does not offer `figures` (the project's
    does), and `figures` run anyway is a one-line error, even with the project installed in editable mode."""
    commands = {}
    for folder in (starter, REPO):
        result = run(["-m", "demo", "--help"], folder)
        assert result.returncode == 0, result.stderr
        commands[folder] = set(re.findall(r"^ {4}(\w+)", result.stdout, flags=re.M))
    assert commands[REPO] - commands[starter] == {"figures"}, commands
    assert {"list", "render", "homework"} <= commands[starter]
    result = run(["-m", "demo", "figures", "--check"], starter)
    assert result.returncode == 2 and result.stderr.splitlines() == [
        "error: `figures` is not available: demo.figures is not in this checkout"], result.stderr


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


def test_graded_tests_pass_on_the_solution(tmp_path):
    score = tmp_path / "score.json"
    result = run(["-m", "pytest", "-q", "-p", "no:cacheprovider", "homework/grading"], REPO,
                 VBD_GRADE_JSON=str(score))
    assert result.returncode == 0, result.stdout[-3000:]
    report = json.loads(score.read_text())
    assert report["earned"] == report["total"] == 100
    assert all(t["passed"] for t in report["tests"].values())


def test_each_task_scores_without_the_tasks_after_it(tmp_path):
    """Tasks 1-3 done and Chebyshev still a TODO: the sweep's tests pass (no kernel of the sweep compiles
    the Chebyshev TODO) and only the Chebyshev tests fail, with their TODO."""
    out = tmp_path / "hw"
    homework.generate(out, quiet=True)
    for task in ("force_hessian", "coloring", "vbd_sweep"):
        implement(out, task)
    score = tmp_path / "score.json"
    run(["-m", "pytest", "-q", "-p", "no:cacheprovider"], out, VBD_GRADE_JSON=str(score))
    report = json.loads(score.read_text())
    tasks = report["tasks"]
    assert all(tasks[t]["earned"] == tasks[t]["points"] for t in ("force_hessian", "coloring", "vbd_sweep")), tasks
    assert tasks["chebyshev"]["earned"] == 0
    chebyshev = [t for t in report["tests"].values() if t["task"] == "chebyshev"]
    assert chebyshev and all(t["reason"].startswith("TODO: chebyshev: ") for t in chebyshev), chebyshev


def test_the_notes_readme_names_every_file_the_starter_cuts_outside_the_solver():
    """lecture_notes/README.md said the starter cuts the solution regions 'of chapters 3, 4 and 6', leaving
    out exercises/analysis.py (task 5, 15 points, measurements from chapters 3 to 6)."""
    text = " ".join((REPO / "lecture_notes" / "README.md").read_text().split())
    for n, task in enumerate(homework.TASKS, start=1):
        for path in sorted({spec.split(":")[0] for spec in task.functions if not spec.startswith("solver/")}):
            assert f"`{path}` (task {n}, {task.points} points)" in text, (task.id, path)


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
    assert (out / "solver" / "physics" / "material.py").exists()


def test_overwrite_replaces_only_what_the_generator_wrote(tmp_path, capsys):
    """--overwrite on an earlier starter deleted the whole folder (shutil.rmtree), a student's notes and
    everything else in it. Now it replaces the files the starter consists of (an edited task file goes back
    to its TODO, as --help says) and removes those an earlier starter wrote, as its marker lists them, that
    this one no longer has; a file the generator did not write is never touched."""
    out = tmp_path / "hw"
    homework.generate(out, quiet=True)
    task_file = out / "solver" / "physics" / "material.py"
    pristine = task_file.read_text()
    task_file.write_text(pristine + "\n# my attempt\n")
    mine = {out / "my_notes.txt": "mine", out / "lecture_notes" / "my_notes.md": "![sketch](missing.png)\n",
            out / "grading" / "my_test.py": "mine", tmp_path / "outside.txt": "mine"}
    for path, text in mine.items():
        path.write_text(text)
    marker = json.loads((out / homework.STARTER_MARKER).read_text())
    (out / "solver" / "dropped.py").write_text("a file of an earlier starter")
    marker.setdefault("files", []).extend(["solver/dropped.py", "../outside.txt", str(tmp_path / "outside.txt")])
    (out / homework.STARTER_MARKER).write_text(json.dumps(marker))
    assert main(["homework", "--out", str(out), "--overwrite"]) == 0
    assert all(path.read_text() == text for path, text in mine.items())
    assert task_file.read_text() == pristine
    assert not (out / "solver" / "dropped.py").exists()
    listed = json.loads((out / homework.STARTER_MARKER).read_text())["files"]
    assert "solver/physics/material.py" in listed and "my_notes.txt" not in listed and "solver/dropped.py" not in listed
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["homework", "--help"])
    helped = " ".join(capsys.readouterr().out.split())
    assert "edits to them are lost" in helped and "files you added are kept" in helped, helped


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
        homework.find_regions(Path("solver/mesh/coloring.py"), source)


def test_markers_in_strings_are_not_regions():
    source = 'def f():\n    """\n    # BEGIN SOLUTION task=coloring\n    """\n    return 1\n'
    assert homework.find_regions(Path("solver/mesh/coloring.py"), source) == []


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


# ---------------------------------------------------------------------------------------------
# Grading for marks: python -m demo homework grade SUBMISSION
# ---------------------------------------------------------------------------------------------
def test_starter_has_no_global_solver(starter, tmp_path):
    assert not (starter / "solver" / "newton").exists()
    for path in [starter / "pyproject.toml", *starter.glob("requirements*.txt")]:
        text = path.read_text()
        assert not any(package in text for package in homework.GLOBAL_SOLVER_PACKAGES), path.name
    assert (starter / "requirements.txt").exists()
    assert '"benchmarks"' not in (starter / "pyproject.toml").read_text()
    assert (starter / "grading" / homework.REFERENCE_FILE).exists()
    for name in (*homework.LICENCE_FILES, "assets/README.md"):        # licence and credits travel with it
        assert (starter / name).exists() == (REPO / name).exists(), name
    for note in (starter / "lecture_notes").glob("*.md"):      # every picture the notes show is in the starter
        for target in re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", note.read_text()):
            assert "://" in target or (note.parent / target).exists(), (note.name, target)
    code = ("import solver\n"
            "from solver import *\n"
            "sim = solver.Simulation(solver.box_mesh(cells=(1, 1, 1)), solver.Material(1e4, 0.3))\n"
            "for call in (lambda: sim.newton_reference(), lambda: solver.newton_solve,\n"
            "             lambda: solver.Simulation(sim.mesh, solver.Material(1e4, 0.3), method='newton')):\n"
            "    try:\n        call()\n    except solver.ConfigError as e:\n        print('refused:', e)\n")
    result = run(["-c", code], as_solution(starter, tmp_path / "solution"))
    refused = [line for line in result.stdout.splitlines() if line.startswith("refused: ")]
    assert len(refused) == 3 and all("this copy has no global solvers" in line for line in refused), result.stderr


def comment_blocks(text: str) -> list:
    """The runs of consecutive comment lines of a requirements or TOML text, each as a tuple of lines."""
    blocks, block = [], []
    for line in text.splitlines() + [""]:
        if line.lstrip().startswith("#"):
            block.append(line)
        elif block:
            blocks.append(tuple(block))
            block = []
    return blocks


def test_starter_requirements_keep_only_whole_comment_blocks(starter):
    """Every comment block of the starter's requirements files and pyproject.toml is one of the project's,
    whole: none is the tail of a block whose first line (naming solver/newton) was cut. A requirements file
    left with only `-r requirements.txt` (requirements-cholmod.txt) is not in the starter."""
    written = [starter / "pyproject.toml", *starter.glob("requirements*.txt")]
    assert {path.name for path in written} == {"pyproject.toml", "requirements.txt", "requirements-mesh.txt"}
    for path in written:
        ours = comment_blocks((REPO / path.name).read_text())
        for block in comment_blocks(path.read_text()):
            assert block in ours, f"{path.name}: a comment block the project's file does not have whole: {block}"


def test_without_global_solvers_drops_the_comment_blocks_of_what_it_drops():
    text = ("# kept: about numpy\nnumpy==1\n"
            "# about the sparse solver of solver/newton/direct.py,\n# continued here\nscipy==1\n"
            "# about qdldl\n# on two lines\nqdldl==0.1\n"
            "# a closing note\n")
    assert homework._without_global_solvers(text) == "# kept: about numpy\nnumpy==1\nscipy==1\n# a closing note\n"


@pytest.mark.parametrize("make, match", [
    (lambda tmp: tmp / "absent", "does not exist"),
    (lambda tmp: (tmp / "file.txt").write_text("x") and tmp / "file.txt", "is not a folder"),
    (lambda tmp: (tmp / "empty").mkdir() or tmp / "empty", "is not a homework starter"),
    (lambda tmp: fake_starter(tmp / "class" / "dave" / "hw").parent.parent, "dave/ holds a starter one level deeper"),
])
def test_grade_refuses_what_is_not_a_submission(tmp_path, capsys, make, match):
    assert main(["homework", "grade", str(make(tmp_path))]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and match in err, err


def fake_starter(folder: Path, marker=True) -> Path:
    """What `submissions` looks at in a starter: solver/ and exercises/, and the marker file."""
    for name in ("solver", "exercises"):
        (folder / name).mkdir(parents=True)
    if marker:
        (folder / homework.STARTER_MARKER).write_text("{}")
    return folder


class FullMarksGrader:
    """Stands in for `homework.Grader`: every submission it is given gets full points."""

    def __init__(self, scratch, root, jobs, timeout):
        pass

    def grade_all(self, submissions, tasks=None, done=None):
        for name in submissions:
            done(name, [homework.TaskGrade(t.id, float(t.points), t.points, 1, 1, "")
                        for t in homework.TASKS if not tasks or t.id in tasks])


def test_every_folder_of_a_class_is_graded_or_reported(tmp_path, capsys, monkeypatch):
    """A starter that lost its hidden marker in a download is graded; one nested a level deeper and an
    empty folder get a line each and 0 points with the reason in the gradebook, and the exit status says
    so. Hidden folders, __MACOSX/ and files are not students."""
    klass = tmp_path / "class"
    fake_starter(klass / "ann")
    fake_starter(klass / "carl", marker=False)
    fake_starter(klass / "dave" / "hw")
    (klass / "erin").mkdir()
    for other in (".git", "__MACOSX"):
        (klass / other).mkdir()
    (klass / "marks.csv").write_text("name,points\n")
    monkeypatch.setattr(homework, "Grader", FullMarksGrader)
    book = tmp_path / "book.json"
    assert main(["homework", "grade", str(klass), "--task", "coloring", "--json", str(book)]) == 1
    out, err = capsys.readouterr()
    assert out.splitlines() == [
        "== ann", "coloring           15/15  1/1 tests passed", "total: 15/15",
        "== carl", "coloring           15/15  1/1 tests passed", "total: 15/15",
        "== dave: 0/15, not graded: dave/ holds a starter one level deeper, in dave/hw/; move its contents up "
        "into dave/ to grade it",
        "== erin: 0/15, not graded: erin/ is empty"], out
    assert err == "not graded: dave, erin (2 of 4 folders, 0 points each; see their lines above)\n", err
    gradebook = json.loads(book.read_text())
    assert list(gradebook) == ["ann", "carl", "dave", "erin"]
    assert [gradebook[name]["earned"] for name in gradebook] == [15, 15, 0, 0]
    assert gradebook["erin"]["not_graded"] == gradebook["erin"]["tasks"]["coloring"]["reason"] == "erin/ is empty"
    assert "not_graded" not in gradebook["carl"]


@pytest.mark.parametrize("where, match", [
    ("notes.txt", "notes.txt already exists; pass --overwrite to replace it"),
    (".", "is a folder; name a file"),
    ("absent/book.json", "absent does not exist"),
    ("notes.txt/book.json", "notes.txt is not a folder"),
])
def test_grade_checks_the_gradebook_path_before_grading(tmp_path, capsys, monkeypatch, where, match):
    """--json refuses an existing file (without --overwrite), a folder and a path in no folder, in one line
    and before any grading; the user's file is untouched."""
    (tmp_path / "notes.txt").write_text("precious")
    graded = []
    monkeypatch.setattr(homework, "Grader", lambda *args, **kw: graded.append(args) or FullMarksGrader(*args, **kw))
    assert main(["homework", "grade", str(fake_starter(tmp_path / "ann")), "--json", str(tmp_path / where)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and match in err, err
    assert graded == [] and (tmp_path / "notes.txt").read_text() == "precious"


def test_grade_replaces_a_gradebook_with_overwrite(tmp_path, capsys, monkeypatch):
    book = tmp_path / "book.json"
    book.write_text("last term's")
    monkeypatch.setattr(homework, "Grader", FullMarksGrader)
    assert main(["homework", "grade", str(fake_starter(tmp_path / "ann")), "--json", str(book), "--overwrite"]) == 0
    assert json.loads(book.read_text())["ann"]["earned"] == 100


@pytest.mark.parametrize("jobs", ["0", "-2"])
def test_grade_refuses_fewer_than_one_job(starter, capsys, jobs):
    assert main(["homework", "grade", str(starter), "--jobs", jobs]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--jobs must be 1 or more, got {jobs}" in err, err


def test_splice_takes_only_the_named_functions():
    pristine = "import a\n\n\n@deco\ndef f(x):\n    raise NotImplementedError\n\n\ndef g():\n    return 1\n"
    submitted = "import evil\n\n\n@other\ndef f(x):\n    y = x\n    return y\n\n\ndef g():\n    return 2\n"
    assert homework.splice(pristine, submitted, ["f"]) == (
        "import a\n\n\n@deco\ndef f(x):\n    y = x\n    return y\n\n\ndef g():\n    return 1\n")
    with pytest.raises(ValueError, match="has no function f"):
        homework.splice(pristine, "def h():\n    pass\n", ["f"])
    with pytest.raises(ValueError, match="does not parse"):
        homework.splice(pristine, "def f(:\n", ["f"])


def test_references_are_solved_once_per_analysis_text(tmp_path):
    """write_references solves its Newton steps once per process and reuses task 5's measurements for the
    same root and exercises/analysis.py text; a changed text is measured again, with the new code."""
    import numpy as np

    root = tmp_path / "root"
    (root / "exercises").mkdir(parents=True)

    def analysis(scale):
        (root / "exercises" / "analysis.py").write_text(
            f"YOUNGS_MODULI = (1e4, 1e5, 1e6)\nRHO_GRID = (0.5, 0.9)\nJACOBI_KEYS = ('start', 'vbd')\n"
            f"def iterations_needed(E):\n    return int(E // 1e4) * {scale}\n"
            f"def rho_residuals():\n    return {{0.5: 1.0 * {scale}, 0.9: 2.0}}\n"
            f"def jacobi_against_coloring():\n    return {{'start': 3.0, 'vbd': 4.0 * {scale}}}\n")

    written = []
    # the changed text has another length: Python's bytecode cache tells a file rewritten within the same
    # second by its size
    for n, scale in enumerate((1, 1, 10)):
        analysis(scale)
        hits = homework._measurements.cache_info().hits
        homework.write_references(tmp_path / f"ref{n}.npz", root)
        written.append(homework._measurements.cache_info().hits - hits)
        with np.load(tmp_path / f"ref{n}.npz") as data:
            assert list(data["iterations_needed"]) == [scale, 10 * scale, 100 * scale]
            assert list(data["rho_residuals"]) == [scale, 2.0]
            assert list(data["jacobi_against_coloring"]) == [3.0, 4 * scale]
            assert set(homework.REFERENCE_CASES) <= set(data.files)
    assert written == [0, 1, 0], "the second file from the memo, the changed analysis measured again"
