"""tools/test_all_pythons.sh: --help and bad arguments answer at once, before any venv is built."""
import os
import shutil
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = "tools/test_all_pythons.sh"

pytestmark = pytest.mark.skipif(not (shutil.which("bash") and shutil.which("sed")), reason="needs bash and sed")


def run(tmp_path, *args):
    """The script with a PATH of bash and sed only and no pyenv: if it went on past its arguments, it would
    find no Python to build a venv with (and say so), not rebuild the real ones for minutes."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    for tool in ("bash", "sed"):
        if not (bin_dir / tool).exists():
            (bin_dir / tool).symlink_to(shutil.which(tool))
    env = dict(PATH=str(bin_dir), HOME=str(tmp_path), PYENV_ROOT=str(tmp_path / "pyenv"),
               VBD_PYTHONS_DIR=str(tmp_path / "venvs"))
    proc = subprocess.run([str(bin_dir / "bash"), SCRIPT, *args], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=30)
    assert not (tmp_path / "venvs").exists(), "it went on to make the venvs folder"
    return proc


@pytest.mark.parametrize("flag", ["-h", "--help"])
def test_help_prints_the_usage_and_does_nothing_else(tmp_path, flag):
    proc = run(tmp_path, flag)
    assert proc.returncode == 0 and proc.stderr == ""
    assert proc.stdout.startswith(f"usage: {SCRIPT} [-h] [-- PYTEST_ARGUMENTS...]\n")
    assert f"{SCRIPT} -- -m \"not slow\"" in proc.stdout


@pytest.mark.parametrize("args", [["--bogus"], ["-m", "not slow"], ["-x", "--"], ["tests/test_mesh.py"]])
def test_an_unknown_argument_is_a_one_line_error(tmp_path, args):
    proc = run(tmp_path, *args)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(f"error: unknown argument '{args[0]}'; "
                                                                   "pytest's arguments go after --")


def test_the_arguments_after_the_double_dash_go_to_pytest(tmp_path):
    proc = run(tmp_path, "--", "-m", "not slow", "--help")
    assert "pytest -m not slow --help\n" in proc.stdout
    assert proc.returncode == 1 and "no CPython 3.10-3.13 found" in proc.stdout     # none on this PATH
