"""What tests/test_homework.py and tests/test_homework_grading.py share: the project folder, a clean
subprocess run, the module's starter and the files the tasks cut."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from demo import homework

REPO = Path(__file__).resolve().parent.parent
TASK_FILES = ("solver/physics/material.py", "solver/mesh/coloring.py", "solver/vbd/vertex_solve.py",
              "solver/vbd/chebyshev.py", "exercises/analysis.py")


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


def as_solution(starter: Path, folder: Path) -> Path:
    """A copy of the starter with the project's own task files dropped in: the solution, as a submission."""
    shutil.copytree(starter, folder)
    for file in TASK_FILES:
        shutil.copyfile(REPO / file, folder / file)
    return folder
