"""Homework starter code: ``python -m demo homework --out DIR [--overwrite]``.

The solver marks each piece students write with a solution region::

    # BEGIN SOLUTION task=force_hessian
    ...the reference solution...
    # END SOLUTION

The generator copies the project into DIR and replaces every region by a comment and
``raise NotImplementedError("TODO: <task>: <what to implement>; see lecture_notes/<chapter>")``.
Regions inside Taichi functions cannot raise at run time, so the solver calls
``solver.todo.require_implemented`` on those functions before it compiles them: the starter stops
with the same message instead of a Taichi compile error.

The starter also gets a student README (the task list, points and how to grade), the graded tests
from ``homework/grading/`` as ``grading/`` and ``grading/reference.npz``, the converged steps the
graded tests compare against (`REFERENCE_CASES`, solved by the project's global Newton when the starter
is written: the starter ships no global solver). ``pytest`` in the starter runs the graded tests and
prints the score per task.

``python -m demo homework grade SUBMISSION`` grades a student's starter (or a folder of them) for
marks: see `grade`.

This module imports nothing heavy: the graded tests read ``TASKS`` from it.
"""
import argparse
import ast
import functools
import io
import json
import re
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
import tokenize
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
GRADING_SOURCE = Path("homework") / "grading"
README_TEMPLATE = Path("homework") / "README.template.md"
STARTER_MARKER = ".vbd-starter.json"

BEGIN = re.compile(r"^(?P<indent>[ \t]*)# BEGIN SOLUTION(?:[ \t]+task=(?P<task>[\w-]+))?[ \t]*$")
END = re.compile(r"^[ \t]*# END SOLUTION[ \t]*$")

# Never copied into a starter: version control, environments, caches, build output, the project's own
# tests (they test the finished solver), the homework sources (solutions to the graded tests' checks).
SKIP_NAMES = {".git", ".venv", "venv", "__pycache__", ".pytest_cache", ".cache", "out", ".ci", "tests",
              "homework", "imgui.ini", ".ipynb_checkpoints", ".DS_Store", "vbd_taichi.egg-info", STARTER_MARKER}
# Folders that hold a task's answer in another form than a solution region; the student README lists
# them with the reason. A starter must carry no task's answer in any form (tests/test_homework.py).
ANSWER_PATHS = {
    Path("benchmarks"): "the benchmarks measure the finished solver, and their baselines "
                        "(`benchmarks/baselines.py`: the VBD sweep in numpy and a Jacobi sweep) are tasks 1 and 3 "
                        "written out",
}
ANSWER_PATHS[Path("solver") / "newton"] = (
    "the global solvers (Newton, Newton-PCG, two-level VBD, the sparse Cholesky) assemble every vertex's "
    "f_i and H_i, tasks 1 and 3 in another form; the graded tests compare against converged steps stored in "
    "`grading/reference.npz` instead, and `method=` other than `'vbd'` and `newton_reference()` stop with "
    "one line")
# Left out because they cannot work without the finished solver and the global solvers; no answer in them.
LEFT_OUT = {
    Path("demo") / "figures.py": "the project's `figures` command, which redraws the lecture figures and checks "
                                 "the notes' numbers, needs the finished solver and the global solvers; the "
                                 "figures it drew are in `lecture_notes/figures/`",
}
SKIP_PATHS = set(ANSWER_PATHS) | set(LEFT_OUT)
# Packages only the global solvers use: not in the starter's pyproject.toml and requirements.txt.
GLOBAL_SOLVER_PACKAGES = ("cvxopt", "qdldl", "cholespy")
REFERENCE_FILE = "reference.npz"
LICENCE_FILES = ("LICENSE", "CITATION.cff")      # copied into the starter with every other root file
SKIP_SUFFIXES = {".pyc", ".pyo", ".mp4", ".gif"}


@dataclass(frozen=True)
class Task:
    """One homework task: the functions whose solution regions it owns, and how it is graded."""

    id: str
    title: str
    points: int
    chapter: str                 # lecture notes chapter that derives it
    functions: tuple             # "solver/file.py:qualified.name" holding this task's regions
    what: dict                   # function name -> one-line description of what to write there
    depends: tuple = ()          # tasks whose code the graded tests of this one also run
    details: str = ""            # a paragraph for the student README
    notes: dict = field(default_factory=dict)   # function name -> extra comment lines in the starter
    chapters: dict = field(default_factory=dict)   # function name -> its chapter, where that is not `chapter`

    def chapter_of(self, function: str) -> str:
        """The chapter that derives `function` (a qualified or plain name), which its TODO points at."""
        return self.chapters.get(function.rsplit(".", 1)[-1], self.chapter)

    def all_chapters(self) -> list:
        """Every chapter the task's TODOs point at, in the notes' order."""
        return sorted({self.chapter, *self.chapters.values()})


TASKS = (
    Task(
        id="force_hessian", title="Per-vertex force and Hessian of the stable Neo-Hookean energy", points=25,
        chapter="lecture_notes/03-coordinate-descent.md",
        functions=("solver/physics/material.py:vertex_force_hessian",),
        what={"vertex_force_hessian": "the contribution of one tet to the force f_i and the 3x3 Hessian H_i "
                                      "of its vertex i"},
        details="Given `F m`, `J = det F`, `w = dJ/dx_i = cof(F) m`, `|m|^2` and the rest volume, return the "
                "tet's contribution to the force `f_i = -dE/dx_i` and the 3x3 Hessian `H_i = d2E/dx_i2` of "
                "the stable Neo-Hookean energy (chapter 3, \"The force and Hessian of one tet\").",
        notes={"vertex_force_hessian": ["Define f (3-vector) and H (3x3 matrix); the line after the region "
                                        "returns them."]},
    ),
    Task(
        id="coloring", title="Greedy graph colouring", points=15,
        chapter="lecture_notes/04-parallelism.md",
        functions=("solver/mesh/coloring.py:_greedy",),
        what={"_greedy": "give vertex order[k] the smallest colour that none of its already coloured "
                         "neighbours has"},
        details="Write the body of the serial loop in `_greedy`: vertex `v = order[k]` gets the smallest "
                "colour not used by any neighbour (CSR arrays `offsets`, `neighbours`); keep `n_colors` "
                "up to date: `_greedy` returns it, `color_vertices` refuses a mesh that needs more than 64 "
                "colours by it, and a graded test checks it (chapter 4, \"Greedy colouring\").",
        notes={"_greedy": ["v = order[k] is the vertex; its neighbours are neighbours[offsets[v]:offsets[v + 1]]; "
                           "colors[u] is -1 until u is coloured.",
                           "Keep n_colors = the number of colours used so far; the function returns it."]},
    ),
    Task(
        id="vbd_sweep", title="The per-colour VBD sweep: assemble and solve each vertex's 3x3 system",
        points=30, chapter="lecture_notes/03-coordinate-descent.md",
        functions=("solver/vbd/vertex_solve.py:force_hessian", "solver/vbd/vertex_solve.py:newton_step"),
        what={"force_hessian": "assemble f_i and H_i of vertex i from its inertia term and the tets "
                               "around it",
              "newton_step": "vertex i's 3x3 Newton step dx = H_i^-1 f_i, zero for a singular H_i"},
        depends=("force_hessian", "coloring"),
        details="In `force_hessian` (solver/vbd/vertex_solve.py), add the inertia term (its force and block are "
                "`inertia_gradient` and `inertia_block` of solver/physics/inertia.py, with m_i/h^2) and loop over the tets around the vertex with `tet_kinematics` and "
                "`vertex_force_hessian`. In `newton_step`, solve the 3x3 system for the step `dx` "
                "(chapter 3, \"The 3x3 Newton solve\", and chapter 4 for why a colour runs in parallel).",
        notes={"force_hessian": ["Define f and H (inertia + elasticity) and H_el (the elastic part alone; "
                                 "the damping term below uses it).",
                                 "Read: x_i is state[X, i] (already in x_i), y_i is state[Y, i], m_i is mass[i]; "
                                 "h, mu and lam are already read from params above.",
                                 "The tets around i are the adjacency entries e in range(offsets[k], "
                                 "offsets[k + 1]): others[e] holds the tet's other three vertices and adj_f[e] "
                                 "its stored data (adj_f[e][M_SQ] = |m|^2, adj_f[e][VOLUME] = rest volume, "
                                 "solver/vbd/layout.py); tet_kinematics (above) turns them into the F m, J and "
                                 "w that vertex_force_hessian (task 1) takes."],
               "newton_step": ["f (3-vector) and H (3x3) are the vertex's force and Hessian from "
                               "force_hessian; define dx (3-vector of type dtype), which the line after the "
                               "region returns. Both sweeps (with and without contact) call this function."]},
    ),
    Task(
        id="chebyshev", title="Chebyshev acceleration", points=15,
        chapter="lecture_notes/06-what-helps.md",
        functions=("solver/vbd/chebyshev.py:chebyshev_omega", "solver/vbd/chebyshev.py:chebyshev_update"),
        what={"chebyshev_omega": "the Chebyshev weight omega_k of iteration k (VBD Eq. 19)",
              "chebyshev_update": "the accelerated update x = omega (x - x^(k-2)) + x^(k-2) and the history "
                                  "shift (VBD Eq. 18)"},
        depends=("force_hessian", "coloring", "vbd_sweep"),
        details="Return the weights `omega_1 = 1`, `omega_2 = 2/(2 - rho^2)`, "
                "`omega_k = 4/(4 - rho^2 omega_(k-1))` and apply the over-relaxation step to every free vertex, "
                "keeping the history rows `X_PREV` = x^(k-1) and `X_PREV2` = x^(k-2) of `state` up to date (chapter 6, "
                "\"Chebyshev acceleration\").",
        notes={"chebyshev_update": ["Update x^(k-2) <- x^(k-1) and x^(k-1) <- the accelerated x as well."]},
    ),
    Task(
        id="analysis", title="Derivations checked numerically, and measurements of your solver", points=15,
        chapter="lecture_notes/03-coordinate-descent.md",
        chapters={"jacobi_against_coloring": "lecture_notes/04-parallelism.md",
                  "iterations_needed": "lecture_notes/05-information-propagation.md",
                  "rho_residuals": "lecture_notes/06-what-helps.md", "best_rho": "lecture_notes/06-what-helps.md"},
        functions=("exercises/analysis.py:dF_dx", "exercises/analysis.py:hessian_eigenvalues",
                   "exercises/analysis.py:iterations_needed", "exercises/analysis.py:rho_residuals",
                   "exercises/analysis.py:best_rho", "exercises/analysis.py:jacobi_against_coloring"),
        what={"dF_dx": "the constant 9x3 matrix d vec(F) / d x_i of one tet",
              "hessian_eigenvalues": "the three eigenvalues of one tet's H_i in closed form",
              "iterations_needed": "count the VBD iterations until max |f_i| drops by REDUCTION",
              "rho_residuals": "max |f_i| after RHO_ITERATIONS accelerated iterations for every rho of RHO_GRID",
              "best_rho": "the best rho of RHO_GRID by rho_residuals",
              "jacobi_against_coloring": "max |f_i| after JACOBI_ITERATIONS iterations of plain and "
                                         "under-relaxed Jacobi (numpy, from sim.local_systems()) and of the "
                                         "coloured sweep"},
        depends=("force_hessian", "coloring", "vbd_sweep", "chebyshev"),
        details="In `exercises/analysis.py`: derive and return the constant matrix dF/dx_i (why J is affine "
                "in x_i, chapter 3) and the eigenvalues of H_i in closed form (why H_i is SPD); then measure "
                "with your solver what the colouring buys (the same vertex solves without colours: Jacobi, "
                "every vertex at once from the same positions, written by you in numpy from "
                "`sim.local_systems()`, plain and under-relaxed, against the coloured sweep, chapter 4), "
                "how many iterations a step needs as E grows (compare with N_c, chapter 5) and which "
                "Chebyshev rho works best (chapter 6). The derivations are checked against finite "
                "differences, the measurements against the project's own within a tolerance, and the "
                "Jacobi measurement also for what chapter 4 finds: plain Jacobi grows or stalls far above "
                "the coloured sweep, and under-relaxed Jacobi converges, but more slowly.",
    ),
)

TASKS_BY_ID = {task.id: task for task in TASKS}


@dataclass(frozen=True)
class ReferenceCase:
    """A cantilever bar whose first converged implicit Euler step the graded tests compare against."""

    cells: tuple                 # (nx, ny, nz) cubes of 6 tets
    size: tuple                  # (lx, ly, lz) in metres
    youngs_modulus: float        # Pa

    def simulation(self, **kwargs):
        import solver

        return cantilever(solver.box_mesh(size=self.size, cells=self.cells), self.youngs_modulus, **kwargs)


REFERENCE_CASES = {
    "soft_bar": ReferenceCase(cells=(8, 2, 2), size=(0.4, 0.1, 0.1), youngs_modulus=1e4),
    "stiff_long_bar": ReferenceCase(cells=(16, 2, 2), size=(0.8, 0.1, 0.1), youngs_modulus=1e6),
}


def cantilever(mesh, youngs_modulus, **kwargs):
    """A `Simulation` of `mesh` pinned at x = min: nu = 0.3, rho = 1000 kg/m^3, h = 1/60 s, inertial guess."""
    import solver

    material = solver.Material(youngs_modulus=youngs_modulus, poisson_ratio=0.3, density=1000.0)
    fixed = mesh.vertices[:, 0] < mesh.vertices[:, 0].min() + 1e-9
    kwargs.setdefault("initial_guess", solver.InitialGuess.INERTIAL)
    return solver.Simulation(mesh, material, dt=1 / 60, fixed=fixed, **kwargs)


def write_references(path: Path, root: Path = REPO_ROOT) -> None:
    """Solve each `REFERENCE_CASES` step to convergence with the project's Newton and save x* (N, 3) per
    case; save the measurements of task 5 made with `root`'s solution. Each is computed once per process
    (the measurements once per text of `exercises/analysis.py`): a script that writes a starter per
    student solves them once."""
    import numpy as np

    np.savez(path, **_newton_references(),
             **_measurements(root.resolve(), (root / "exercises" / "analysis.py").read_text()))


@functools.lru_cache(maxsize=1)
def _newton_references() -> dict:
    """{case name: x* (N, 3)} for `write_references`."""
    import solver

    solver.ensure_taichi("cpu")
    return {name: case.simulation().newton_reference() for name, case in REFERENCE_CASES.items()}


@functools.lru_cache(maxsize=4)
def _measurements(root: Path, analysis_source: str) -> dict:
    """`measurements(root)` for `write_references`; `analysis_source` is only the key."""
    return measurements(root)


def measurements(root: Path = REPO_ROOT) -> dict:
    """Task 5's measurements made with `root`'s `exercises/analysis.py`: {"iterations_needed": (3,)
    counts for analysis.YOUNGS_MODULI, "rho_residuals": (6,) newtons for analysis.RHO_GRID,
    "jacobi_against_coloring": (4,) newtons for analysis.JACOBI_KEYS}."""
    import importlib.util

    import numpy as np

    spec = importlib.util.spec_from_file_location("_solution_analysis", root / "exercises" / "analysis.py")
    analysis = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(analysis)
    residuals, sweeps = analysis.rho_residuals(), analysis.jacobi_against_coloring()
    return {"iterations_needed": np.array([analysis.iterations_needed(E) for E in analysis.YOUNGS_MODULI]),
            "rho_residuals": np.array([residuals[rho] for rho in analysis.RHO_GRID]),
            "jacobi_against_coloring": np.array([sweeps[key] for key in analysis.JACOBI_KEYS])}


def _error(message):
    from .errors import DemoError

    return DemoError(message)


def todo_message(task: Task, function: str) -> str:
    """The text of the NotImplementedError that replaces a region of `task` inside `function`."""
    short = function.rsplit(".", 1)[-1]
    message = f"TODO: {task.id}: {short}: {task.what[short]}; see {task.chapter_of(function)}"
    assert '"' not in message and "\\" not in message, message
    return message


@dataclass
class Region:
    path: Path           # relative to the project root
    task: Task
    function: str        # qualified name of the enclosing function
    start: int           # 1-based line of BEGIN
    end: int             # 1-based line of END
    lines: list          # the solution lines between the markers


def _enclosing_functions(source: str):
    """[(first line, last line, qualified name)] of every function in a module, innermost last."""
    found = []

    def visit(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    found.append((child.lineno, child.end_lineno, name))
                visit(child, name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return found


@functools.lru_cache(maxsize=256)
def _comment_lines(text: str) -> frozenset:
    """Line numbers that hold only a comment (cached by text: every grading splices the same files)."""
    return frozenset(token.start[0] for token in tokenize.generate_tokens(io.StringIO(text).readline)
                     if token.type == tokenize.COMMENT and not token.line[:token.start[1]].strip())


def find_regions(path: Path, text: str, root: Path = REPO_ROOT):
    """The solution regions of one Python file, checked: balanced, task known, inside a task's function."""
    lines = text.splitlines()
    comments = _comment_lines(text)
    regions, open_at, task = [], None, None
    functions = None
    for number, line in enumerate(lines, start=1):
        if number not in comments:
            continue           # a marker quoted in a string or docstring is not a marker
        begin, end = BEGIN.match(line), END.match(line)
        if begin:
            if open_at is not None:
                raise _error(f"{path}:{number}: BEGIN SOLUTION inside the region opened on line {open_at}")
            task_id = begin["task"]
            if task_id not in TASKS_BY_ID:
                raise _error(f"{path}:{number}: solution region needs task=ID with ID one of "
                             f"{', '.join(TASKS_BY_ID)}, got {task_id!r}")
            open_at, task = number, TASKS_BY_ID[task_id]
        elif end:
            if open_at is None:
                raise _error(f"{path}:{number}: END SOLUTION without BEGIN SOLUTION")
            if functions is None:
                functions = _enclosing_functions(text)
            inside = [name for first, last, name in functions if first <= open_at <= last]
            if not inside:
                raise _error(f"{path}:{open_at}: solution region outside any function")
            function = inside[-1]
            if f"{path.as_posix()}:{function}" not in task.functions:
                raise _error(f"{path}:{open_at}: region of task {task.id} is in {function}, which the task "
                             f"does not list (TASKS in demo/homework.py)")
            regions.append(Region(path, task, function, open_at, number, lines[open_at:number - 1]))
            open_at = None
    if open_at is not None:
        raise _error(f"{path}:{open_at}: BEGIN SOLUTION is never closed")
    return regions


def strip_regions(text: str, regions) -> str:
    """`text` with each region replaced by its TODO comment and raise."""
    lines = text.splitlines(keepends=True)
    out, cursor = [], 0
    for region in regions:
        out.extend(lines[cursor:region.start - 1])
        indent = BEGIN.match(lines[region.start - 1].rstrip("\n"))["indent"]
        short = region.function.rsplit(".", 1)[-1]
        comment = [f"TODO(task {region.task.id}, {region.task.points} points): {region.task.what[short]}.",
                   *region.task.notes.get(short, []),
                   f"Replace the raise below with your code; see {region.task.chapter_of(region.function)}."]
        for paragraph in comment:
            for line in textwrap.wrap(paragraph, width=max(40, 100 - len(indent)), break_on_hyphens=False):
                out.append(f"{indent}# {line}\n")
        out.append(f'{indent}raise NotImplementedError("{todo_message(region.task, region.function)}")\n')
        cursor = region.end
    out.extend(lines[cursor:])
    return "".join(out)


def project_files(root: Path, exclude: Path = None):
    """Every file of the project that belongs in a starter, as paths relative to `root`, sorted."""
    result = []

    def walk(folder: Path):
        for entry in sorted(folder.iterdir()):
            rel = entry.relative_to(root)
            if entry.name in SKIP_NAMES or rel in SKIP_PATHS or entry.is_symlink():
                continue
            if exclude is not None and entry.resolve() == exclude:
                continue
            if entry.is_dir():
                walk(entry)
            elif entry.is_file() and entry.suffix not in SKIP_SUFFIXES:
                result.append(rel)

    walk(root)
    return result


def all_regions(root: Path = REPO_ROOT):
    """Every solution region under `root`'s Python files, in file and line order."""
    regions = []
    for rel in project_files(root):
        if rel.suffix == ".py":
            text = (root / rel).read_text(encoding="utf-8")
            if "SOLUTION" in text:
                regions += find_regions(rel, text, root)
    return regions


def _check_output(out: Path, root: Path, overwrite: bool):
    out = out.resolve()
    if out == root or root.is_relative_to(out):
        raise _error(f"refusing to write the starter into {out}: it contains the project itself")
    if out.exists() and not out.is_dir():
        raise _error(f"{out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise _error(f"{out} is not empty; pass --overwrite to replace the starter's files in it (files you added "
                     "are kept) or --out to choose another folder")
    return out


def _earlier_files(out: Path) -> set:
    """The files (relative to `out`) that an earlier starter in `out` wrote, as its marker lists them: none
    where there is no marker, it cannot be read or it is from a generator that kept no list."""
    try:
        listed = json.loads((out / STARTER_MARKER).read_text(encoding="utf-8")).get("files", [])
    except (OSError, ValueError, AttributeError):
        return set()
    return {Path(name) for name in listed if isinstance(name, str) and not Path(name).is_absolute()
            and ".." not in Path(name).parts}


def _student_readme(root: Path, regions) -> str:
    rows, sections = [], []
    for n, task in enumerate(TASKS, start=1):
        places = sorted({f"`{r.path.as_posix()}` `{r.function}`" for r in regions if r.task is task})
        needs = ", ".join(f"`{d}`" for d in task.depends) or "-"
        rows.append(f"| {n} | `{task.id}` | {task.title} | {task.points} | {', '.join(places)} | {needs} |")
        sections.append(f"### {n}. {task.title} (`{task.id}`, {task.points} points)\n\n{task.details}\n\n"
                        f"Where: {', '.join(places)}. Read: "
                        f"{', '.join(f'[{chapter}]({chapter})' for chapter in task.all_chapters())}.\n")
    total = sum(task.points for task in TASKS)
    template = (root / README_TEMPLATE).read_text(encoding="utf-8")
    table = ("| # | task | what | points | where | graded with |\n|---|---|---|---|---|---|\n"
             + "\n".join(rows) + f"\n| | | **total** | **{total}** | | |")
    left_out = "\n".join([f"* `{path.as_posix()}/`: {why}." for path, why in sorted(ANSWER_PATHS.items())]
                         + [f"* `{path.as_posix()}`: {why}." for path, why in sorted(LEFT_OUT.items())])
    licence_files = [f"`{name}`" for name in LICENCE_FILES if (root / name).exists()]
    licence = (f"The project's {' and '.join(licence_files)} apply to this copy as well." if licence_files else
               "The project carries no licence file yet; ask your instructor before you share this copy.")
    template = template.replace("{{LICENCE}}", licence)
    return (template.replace("{{TASK_TABLE}}", table).replace("{{TASK_SECTIONS}}", "\n".join(sections))
            .replace("{{TOTAL}}", str(total)).replace("{{LEFT_OUT}}", left_out))


def _pytest_ini(text: str) -> str:
    """The project's pytest.ini pointed at the graded tests."""
    if re.search(r"^testpaths\s*=.*$", text, flags=re.M):
        return re.sub(r"^testpaths\s*=.*$", "testpaths = grading", text, flags=re.M)
    return text.rstrip("\n") + "\ntestpaths = grading\n"


def _without_global_solvers(text: str) -> str:
    """A requirements or pyproject text without the lines naming the global solvers or their packages. A
    comment block (comment lines in a row) goes whole: when one of its lines names them, and with the line
    right after it, which it describes, when that line goes."""
    dropped = (*GLOBAL_SOLVER_PACKAGES, "solver/newton", "solver.newton")

    def names(lines):
        return any(word in line for line in lines for word in dropped)

    kept, block = [], []
    for line in text.splitlines(keepends=True):
        if line.lstrip().startswith("#"):
            block.append(line)
            continue
        if not names([line]):
            kept += [] if names(block) else block
            kept.append(line)
        block = []
    kept += [] if names(block) else block
    return "".join(kept).replace(', "benchmarks"]', "]")


def _is_requirement(line: str) -> bool:
    """Whether a requirements-file line asks for a package (not blank, a comment or an -r include)."""
    return bool(line.strip()) and not line.lstrip().startswith(("#", "-r", "--requirement"))


def generate(out: Path, overwrite: bool = False, root: Path = REPO_ROOT, quiet: bool = False):
    """Write the starter into `out`; returns the list of regions replaced."""
    root = root.resolve()
    out = _check_output(Path(out), root, overwrite)
    files = project_files(root, exclude=out)
    by_file, regions = {}, []
    for rel in files:
        if rel.suffix == ".py":
            text = (root / rel).read_text(encoding="utf-8")
            found = find_regions(rel, text, root) if "SOLUTION" in text else []
            if found:
                by_file[rel] = (text, found)
                regions += found
    missing = [task.id for task in TASKS if not any(r.task is task for r in regions)]
    if missing:
        raise _error(f"no solution region for task(s) {', '.join(missing)} under {root}; "
                     "is this already a starter copy?")
    earlier = _earlier_files(out)
    written = {Path(STARTER_MARKER)}     # every file this starter consists of, relative to `out`

    def copy(source, target):
        written.add(Path(target).relative_to(out))
        return shutil.copy2(source, target)

    try:
        out.mkdir(parents=True, exist_ok=True)
        for rel in files:
            target = out / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            if rel in by_file:
                text, found = by_file[rel]
                target.write_text(strip_regions(text, found), encoding="utf-8")
            elif rel == Path("pytest.ini"):
                target.write_text(_pytest_ini((root / rel).read_text(encoding="utf-8")), encoding="utf-8")
            elif rel.name == "pyproject.toml" or (rel.name.startswith("requirements") and rel.suffix == ".txt"):
                text = _without_global_solvers((root / rel).read_text(encoding="utf-8"))
                if rel.suffix == ".txt" and not any(_is_requirement(line) for line in text.splitlines()):
                    continue          # a requirements file of the global solvers only
                target.write_text(text, encoding="utf-8")
            else:
                shutil.copyfile(root / rel, target)
            written.add(rel)
        if not (root / "pytest.ini").exists():
            (out / "pytest.ini").write_text("[pytest]\ntestpaths = grading\n", encoding="utf-8")
            written.add(Path("pytest.ini"))
        grading = root / GRADING_SOURCE
        shutil.copytree(grading, out / "grading", dirs_exist_ok=True, copy_function=copy,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc", ".pytest_cache"))
        write_references(out / "grading" / REFERENCE_FILE, root)
        written.add(Path("grading") / REFERENCE_FILE)
        _refresh_starter_notes(out, [out / rel for rel in sorted(written)
                                     if rel.parent == Path("lecture_notes") and rel.suffix == ".md"])
        if (root / "README.md").exists():
            shutil.copyfile(root / "README.md", out / "PROJECT_README.md")
            _drop_missing_pictures(out / "PROJECT_README.md")
            written.add(Path("PROJECT_README.md"))
        (out / "README.md").write_text(_student_readme(root, regions), encoding="utf-8")
        written.add(Path("README.md"))
        (out / STARTER_MARKER).write_text(json.dumps(
            {"tasks": [t.id for t in TASKS],
             "regions": [{"file": r.path.as_posix(), "function": r.function, "task": r.task.id} for r in regions],
             "files": sorted(rel.as_posix() for rel in written)},
            indent=2) + "\n", encoding="utf-8")
        for rel in sorted(earlier - written):     # an earlier starter's files that this one no longer has
            if (out / rel).is_file():
                (out / rel).unlink()
    except OSError as e:
        raise _error(f"cannot write the starter into {out}: {e.strerror or e}") from None
    if not quiet:
        print(f"wrote the homework starter to {out}: {len(regions)} solution regions in {len(by_file)} files "
              f"replaced, {len(TASKS)} tasks, {sum(t.points for t in TASKS)} points")
        print(f"students: read {out / 'README.md'}; grade with `.venv/bin/python -m pytest` inside {out}")
    return regions


IMAGE = re.compile(r"!\[(?P<alt>[^\]]*)\]\((?P<target>[^)\s]+)\)")


def _refresh_starter_notes(out: Path, paths):
    """Re-quote the code excerpts of the starter's lecture notes (`paths`, the .md files it wrote into
    lecture_notes/) from the starter's own sources, so that the notes show the TODOs and no solution code;
    an excerpt of a file or a picture the starter leaves out becomes a line saying so."""
    from .notes_sync import EXCERPT, chapters, function_source

    def excerpt(match):
        if not (out / match["path"]).exists():
            return f"*(`{match['path']}` is not in the homework starter; see its README)*"
        return match.group(1) + function_source(out / match["path"], match["name"]) + match.group(5)

    for path in paths:
        text = path.read_text(encoding="utf-8")
        if path in chapters(out / "lecture_notes"):
            text = EXCERPT.sub(excerpt, text)
        path.write_text(text, encoding="utf-8")
        _drop_missing_pictures(path)


def _drop_missing_pictures(path: Path):
    """Replace each picture link of the Markdown file `path` whose file is absent by a line saying so."""
    def image(match):
        if "://" in match["target"] or (path.parent / match["target"]).exists():
            return match.group(0)
        return f"*(picture left out of the homework starter: {match['alt']})*"

    path.write_text(IMAGE.sub(image, path.read_text(encoding="utf-8")), encoding="utf-8")


def describe_not_implemented(error: BaseException) -> str:
    """The one line `python -m demo` prints when starter code reaches a TODO."""
    text = str(error)
    return "not yet implemented: " + (text[len("TODO: "):] if text.startswith("TODO: ") else text)


# ---------------------------------------------------------------------------------------------
# Grading for marks: python -m demo homework grade SUBMISSION
# ---------------------------------------------------------------------------------------------
GRADE_TIMEOUT_S = 300      # default of --timeout: a task's graded tests take seconds, a minute with cold compiles


@dataclass(frozen=True)
class TaskGrade:
    """The points of one task of one submission, and the first reason it lost some."""

    task: str
    earned: float
    points: int
    passed: int
    total: int
    reason: str


def _functions(text: str) -> dict:
    """{qualified name: (line of `def`, last line)} of every function of a module (1-based)."""
    return {name: (first, last) for first, last, name in _enclosing_functions(text)}


def splice(pristine: str, submitted: str, names) -> str:
    """`pristine` with the functions `names` (qualified) replaced, `def` line to last line, by the
    submission's; decorators stay the pristine ones. Raises ValueError naming what is missing."""
    try:
        theirs = _functions(submitted)
    except SyntaxError as e:
        raise ValueError(f"does not parse (line {e.lineno}: {e.msg})") from None
    ours = _functions(pristine)
    lines, their_lines = pristine.splitlines(keepends=True), submitted.splitlines(keepends=True)
    for name in sorted(names, key=lambda n: ours[n][0], reverse=True):
        if name not in theirs:
            raise ValueError(f"has no function {name}")
        first, last = ours[name]
        their_first, their_last = theirs[name]
        lines[first - 1:last] = their_lines[their_first - 1:their_last]
    return "".join(lines)


def _task_files(task: Task) -> dict:
    """{file: [qualified function names]} of the functions a task owns."""
    files = {}
    for spec in task.functions:
        path, name = spec.split(":")
        files.setdefault(path, []).append(name)
    return files


# The top folders of the task files: a folder holding one of them is a submission, with or without the marker
# (a zip or LMS download often loses hidden files).
TASK_FOLDERS = tuple(sorted({Path(spec.split(":")[0]).parts[0] for task in TASKS for spec in task.functions}))
# A class folder's subfolders that are never a student's: hidden ones (.git, ...) and the metadata folder
# macOS puts into zip files.
NOT_STUDENTS = re.compile(r"\..*|__MACOSX")


def _is_starter(folder: Path) -> bool:
    """Whether `folder` is a student's starter: it holds the marker or a folder of task files."""
    return (folder / STARTER_MARKER).is_file() or any((folder / name).is_dir() for name in TASK_FOLDERS)


def _task_folder_names() -> str:
    return " or ".join(f"{name}/" for name in TASK_FOLDERS)


def _not_a_starter(folder: Path) -> str:
    """Why the folder `folder` of a class cannot be graded, in words that start with its name."""
    name = f"{folder.name}/"
    entries = sorted(folder.iterdir())
    if not entries:
        return f"{name} is empty"
    nested = [entry for entry in entries if entry.is_dir() and _is_starter(entry)]
    if nested:
        return (f"{name} holds a starter one level deeper, in {name}{nested[0].name}/; move its contents up into "
                f"{name} to grade it")
    return f"{name} is not a homework starter (no {STARTER_MARKER}, {_task_folder_names()} in it)"


def submissions(path: Path) -> tuple:
    """({name: folder} of the starters to grade, {name: why not} of a class's folders that cannot be
    graded): `path` itself when it is a starter, else every folder directly inside it (a class) but
    hidden ones and __MACOSX/."""
    if not path.exists():
        raise _error(f"{path} does not exist; pass a student's starter folder or a folder of them")
    if not path.is_dir():
        raise _error(f"{path} is not a folder; pass a student's starter folder or a folder of them")
    if _is_starter(path):
        return {path.resolve().name: path}, {}
    found, skipped = {}, {}
    for child in sorted(path.iterdir(), key=lambda child: child.name):
        if not child.is_dir() or NOT_STUDENTS.fullmatch(child.name):
            continue
        try:
            if _is_starter(child):
                found[child.name] = child
            else:
                skipped[child.name] = _not_a_starter(child)
        except OSError as e:
            skipped[child.name] = f"{child.name}/ cannot be read ({e.strerror or e})"
    if not found:
        why = f" ({next(iter(skipped.values()))}{f', and {len(skipped) - 1} more' if len(skipped) > 1 else ''})" \
            if skipped else ""
        raise _error(f"{path} is not a homework starter (no {STARTER_MARKER}, {_task_folder_names()}) and holds none"
                     f"{why}; pass the folder `python -m demo homework --out` wrote, or a folder of such folders")
    return found, skipped


class Grader:
    """Grades submissions in a scratch folder: one fresh starter per task, in which that task's functions
    come from the submission and every other task's from the solution, so a bug costs only its own task.

    Nothing else of a submission is used: its conftest.py, ini files, grading/ and other files never reach
    the tree the grader runs in, and pytest runs with a clean environment (no plugin autoload, no
    PYTEST_ADDOPTS or PYTHONPATH) from that tree. Up to `jobs` such runs go at once, each in its own tree;
    a run still going after `timeout` seconds (a submission's endless loop) is stopped and scores 0.
    """

    def __init__(self, scratch: Path, root: Path = REPO_ROOT, jobs: int = 1, timeout: float = GRADE_TIMEOUT_S):
        self.root = root.resolve()
        self.scratch = Path(scratch)
        self.jobs = jobs
        self.timeout = timeout
        self.starter = self.scratch / "starter"
        generate(self.starter, root=self.root, quiet=True)
        self.pristine = {task.id: {file: (self.starter / file).read_text(encoding="utf-8") for file in _task_files(task)}
                         for task in TASKS}
        self._graded = {}        # (task, its spliced files) -> TaskGrade: the graded tests are deterministic
        self._runs = 0

    def _tree(self, task: Task, spliced: dict, run: int) -> Path:
        """A fresh copy of the starter with `task`'s files `spliced` and every other task's solution:
        fresh for every run, so nothing a graded submission wrote reaches the next one."""
        tree = self.scratch / f"run-{run}-{task.id}"
        shutil.copytree(self.starter, tree, symlinks=True)
        for other in TASKS:
            if other is not task:
                for file in _task_files(other):
                    shutil.copyfile(self.root / file, tree / file)
        for file, text in spliced.items():
            (tree / file).write_text(text, encoding="utf-8")
        return tree

    def _run(self, task: Task, spliced: dict, run: int) -> TaskGrade:
        """Grade `task` with its files `spliced`, in a fresh tree that is removed afterwards."""
        tree = self._tree(task, spliced, run)
        try:
            return self._pytest(task, tree, tree.with_name(tree.name + ".json"))
        finally:
            shutil.rmtree(tree, ignore_errors=True)

    def _pytest(self, task: Task, tree: Path, report: Path) -> TaskGrade:
        tests = sorted((tree / "grading").glob(f"test_*_{task.id}.py"))
        report.unlink(missing_ok=True)
        env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "PYTEST", "VBD_", "COV_"))}
        env.update(PYTEST_DISABLE_PLUGIN_AUTOLOAD="1", PYTHONDONTWRITEBYTECODE="1", VBD_GRADE_JSON=str(report))
        command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(tree),
                   "-c", str(tree / "pytest.ini"), *[str(t.relative_to(tree)) for t in tests]]
        try:
            result = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True,
                                    timeout=self.timeout)
        except subprocess.TimeoutExpired:
            return TaskGrade(task.id, 0.0, task.points, 0, 0, f"the graded tests ran past {self.timeout:g} s "
                                                               "(an endless loop?); stopped")
        if not report.exists():
            last = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
            return TaskGrade(task.id, 0.0, task.points, 0, 0,
                             f"the graded tests did not run: {last[-1][:160] if last else 'no output'}")
        row = json.loads(report.read_text())["tasks"].get(task.id)
        report.unlink()
        if row is None:
            return TaskGrade(task.id, 0.0, task.points, 0, 0, "no graded test of this task ran")
        return TaskGrade(task.id, float(row["earned"]), task.points, row["passed"], row["total"], row["reason"])

    def _plan(self, submission: Path, task: Task):
        """The TaskGrade of a submission whose task files cannot be used, else the key of its graded run:
        (task id, its spliced files)."""
        spliced = {}
        try:
            for file, names in _task_files(task).items():
                source = submission / file
                if not source.is_file():
                    raise ValueError(f"{file} is missing")
                try:
                    text = source.read_text(encoding="utf-8")
                except (OSError, UnicodeDecodeError) as e:
                    raise ValueError(f"{file} cannot be read ({e})") from None
                try:
                    spliced[file] = splice(self.pristine[task.id][file], text, names)
                except ValueError as e:
                    raise ValueError(f"{file} {e}") from None
        except ValueError as e:
            return TaskGrade(task.id, 0.0, task.points, 0, 0, str(e))
        return task.id, tuple(sorted(spliced.items()))

    def grade_all(self, submissions: dict, tasks=None, done=None) -> dict:
        """{name: [TaskGrade] in task order} of each starter folder of `submissions` ({name: folder});
        `tasks`: ids to grade (default all). Up to `jobs` graded runs at once; `done(name, grades)` is
        called for each submission in order, as soon as it and those before it are graded."""
        plans = {name: [self._plan(folder, task) for task in TASKS if not tasks or task.id in tasks]
                 for name, folder in submissions.items()}
        books, runs = {}, {}
        pool = ThreadPoolExecutor(max_workers=self.jobs)
        try:
            for plan in plans.values():
                for key in plan:
                    if not isinstance(key, TaskGrade) and key not in self._graded and key not in runs:
                        self._runs += 1
                        runs[key] = pool.submit(self._run, TASKS_BY_ID[key[0]], dict(key[1]), self._runs)
            for name, plan in plans.items():
                for key in plan:
                    if key in runs:
                        self._graded[key] = runs[key].result()
                books[name] = [key if isinstance(key, TaskGrade) else self._graded[key] for key in plan]
                if done is not None:
                    done(name, books[name])
        finally:       # on Ctrl-C or an error, start no further run; those running finish
            pool.shutdown(wait=True, cancel_futures=True)
        return books

    def grade(self, submission: Path, tasks=None) -> list:
        """[TaskGrade] of one student's starter folder, in task order; `tasks`: ids to grade (default all)."""
        return self.grade_all({"": submission}, tasks)[""]


def _points(value: float) -> str:
    return f"{value:.0f}" if abs(value - round(value)) < 1e-9 else f"{value:.1f}"


def _check_gradebook(json_file: Path, overwrite: bool):
    """Refuse a --json path that cannot take the gradebook, before any grading: a folder, one whose folder
    does not exist, or an existing file unless `overwrite`."""
    parent = json_file.parent
    if json_file.is_dir():
        raise _error(f"--json {json_file} is a folder; name a file, for example --json {json_file / 'gradebook.json'}")
    if not parent.is_dir():
        raise _error(f"--json {json_file}: {parent} {'is not a folder' if parent.exists() else 'does not exist'}; "
                     "name a file in an existing folder")
    if json_file.exists() and not overwrite:
        raise _error(f"--json {json_file} already exists; pass --overwrite to replace it or name another file")


def grade(submission: Path, json_file: Path = None, tasks=None, root: Path = REPO_ROOT, jobs: int = 1,
          overwrite: bool = False, timeout: float = GRADE_TIMEOUT_S) -> dict:
    """Grade a starter folder or a class (a folder of them), `jobs` graded runs at once, each stopped after
    `timeout` seconds (0 points for its task); print each task's
    points and `total: NN/100` last. Every folder of a class is graded or reported: one that is not a
    starter (see `submissions`) gets one line saying why and 0 points. Returns {name: {"tasks": {task:
    TaskGrade fields}, "earned", "total"}, plus "not_graded": why for a folder that was not graded};
    `json_file` gets the same (an existing one only with `overwrite`)."""
    folders, skipped = submissions(Path(submission))
    if json_file is not None:
        _check_gradebook(Path(json_file), overwrite)
    selected = [task for task in TASKS if not tasks or task.id in tasks]
    book = {}

    def entry(grades):
        return {"tasks": {g.task: {k: v for k, v in g.__dict__.items() if k != "task"} for g in grades},
                "earned": sum(g.earned for g in grades), "total": sum(g.points for g in grades)}

    def report(name, grades):
        if len(folders) + len(skipped) > 1:
            print(f"== {name}")
        for g in grades:
            why = f"   {g.reason}" if g.earned < g.points and g.reason else ""
            print(f"{g.task:15s} {_points(g.earned):>5s}/{g.points:<3d} {g.passed}/{g.total} tests passed{why}")
        book[name] = entry(grades)
        print(f"total: {_points(book[name]['earned'])}/{book[name]['total']}", flush=True)

    def not_graded(name):
        why = skipped[name]
        book[name] = {**entry([TaskGrade(task.id, 0.0, task.points, 0, 0, why) for task in selected]),
                      "not_graded": why}
        print(f"== {name}: 0/{book[name]['total']}, not graded: {why}", flush=True)

    waiting = sorted(skipped)

    def done(name, grades):        # the class in name order, the folders not graded among the others
        while waiting and waiting[0] < name:
            not_graded(waiting.pop(0))
        report(name, grades)

    with tempfile.TemporaryDirectory(prefix="vbd-grade-") as scratch:
        Grader(Path(scratch), root=root, jobs=jobs, timeout=timeout).grade_all(folders, tasks, done=done)
    while waiting:
        not_graded(waiting.pop(0))
    if json_file is not None:
        try:
            Path(json_file).write_text(json.dumps(book, indent=2) + "\n", encoding="utf-8")
        except OSError as e:
            raise _error(f"cannot write the gradebook {json_file}: {e.strerror or e}") from None
    return book


def grade_main(argv) -> int:
    from .cli import HelpFormatter, Parser

    parser = Parser(
        prog="python -m demo homework grade", formatter_class=HelpFormatter,
        description="Grade homework for marks: copy only the task functions of each submission into a fresh "
                    "starter built from this project (one per task, the other tasks' solutions in place) and "
                    "run the pristine graded tests there. Prints the points per task and, last, total: NN/100. "
                    "A class folder: every folder in it is a submission (hidden folders and __MACOSX/ aside). "
                    f"One holding {_task_folder_names()} is graded, with or without its {STARTER_MARKER} (a zip "
                    "or LMS download may drop that hidden file); any other (empty, or the starter one level "
                    "deeper) gets one line saying why and 0 points in the gradebook, and the command exits "
                    "with status 1 once the rest is graded.")
    parser.add_argument("submission", type=Path, help="a student's starter folder, or a folder of them (a class)")
    parser.add_argument("--json", type=Path, default=None, metavar="FILE",
                        help="also write the gradebook as JSON (default: none)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --json FILE")
    parser.add_argument("--task", action="append", choices=list(TASKS_BY_ID), default=None,
                        help="grade only this task (repeatable; default: all tasks)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1, metavar="N",
                        help="graded runs at once, each a pytest process of about 170 MB (default: this machine's "
                             "CPU count, %(default)s)")
    parser.add_argument("--timeout", type=float, default=GRADE_TIMEOUT_S, metavar="SECONDS",
                        help="stop a task's graded run after this long and give it 0 points (a submission's "
                             "endless loop)")
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error(f"--jobs must be 1 or more, got {args.jobs}")
    if not 0 < args.timeout < float("inf"):
        parser.error(f"--timeout must be a positive number of seconds, got {args.timeout:g}")
    book = grade(args.submission, args.json, args.task, jobs=args.jobs, overwrite=args.overwrite,
                 timeout=args.timeout)
    missed = [name for name, entry in book.items() if "not_graded" in entry]
    if missed:
        print(f"not graded: {', '.join(missed)} ({len(missed)} of {len(book)} folders, 0 points each; "
              "see their lines above)", file=sys.stderr)
        return 1
    return 0


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["grade"]:
        return grade_main(argv[1:])
    parser = argparse.ArgumentParser(
        prog="python -m demo homework", formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Write a homework starter copy of this project: every solution region in the solver is "
                    "replaced by a TODO, plus a student README and the graded tests (grading/). "
                    "`python -m demo homework grade SUBMISSION` grades students' starters for marks.")
    parser.add_argument("--out", type=Path, default=Path("out") / "homework",
                        help="folder to write the starter into")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a folder that is not empty: every file of the starter is replaced, the "
                             "solver files with TODOs included (edits to them are lost), and the files an earlier "
                             "starter there wrote that this one has no more are removed; files you added are kept")
    parser.add_argument("--list", action="store_true", help="list the tasks and their solution regions, write nothing")
    args = parser.parse_args(argv)
    if args.list:
        regions = all_regions()
        for task in TASKS:
            print(f"{task.id:14s} {task.points:3d} points  {task.title}")
            for r in regions:
                if r.task is task:
                    lines = f"{len(r.lines)} line{'s' if len(r.lines) != 1 else ''}"
                    print(f"{'':20s}{r.path.as_posix()}:{r.start}-{r.end} {r.function} ({lines})")
        return 0
    generate(args.out, overwrite=args.overwrite)
    return 0


if __name__ == "__main__":
    sys.exit(main())
