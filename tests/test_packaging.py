"""requirements.txt and pyproject.toml agree on the supported Pythons and on the packages: every
supported CPython gets exactly one exact pin per package, every other one the one-line stop."""
from pathlib import Path
from urllib.parse import unquote

import pytest
from packaging.markers import default_environment
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet

ROOT = Path(__file__).resolve().parent.parent
SUPPORTED = ["3.10", "3.11", "3.12", "3.13"]
CHECKED = [f"3.{minor}" for minor in range(6, 16)]


def requirements():
    """The requirements of requirements.txt, in file order."""
    lines = (line.split(" #")[0].strip() for line in (ROOT / "requirements.txt").read_text().splitlines())
    return [Requirement(line) for line in lines if line and not line.startswith(("#", "-"))]


def active(version):
    env = dict(default_environment(), python_version=version, python_full_version=version + ".0")
    return [r for r in requirements() if r.marker is None or r.marker.evaluate(env)]


def pyproject():
    tomllib = pytest.importorskip("tomllib", reason="tomllib is in the standard library from Python 3.11")
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


@pytest.mark.parametrize("version", CHECKED)
def test_each_python_gets_exact_pins_or_the_one_line_stop(version):
    reqs = active(version)
    guards = [r for r in reqs if r.url]
    if version in SUPPORTED:
        assert guards == []
        names = [r.name.lower() for r in reqs]
        assert len(names) == len(set(names)), f"two pins for one package on {version}: {names}"
        assert all(len(r.specifier) == 1 and next(iter(r.specifier)).operator == "==" for r in reqs), reqs
    else:
        assert len(guards) == 1 and reqs[0] is guards[0], "the stop must be the first requirement"
        message = unquote(guards[0].url)
        assert "3.10, 3.11, 3.12 or 3.13" in message and "pyenv install 3.13" in message, message


def test_requires_python_says_the_same():
    spec = SpecifierSet(pyproject()["requires-python"])
    assert [v for v in CHECKED if spec.contains(v + ".0")] == SUPPORTED


def test_pyproject_ranges_hold_every_pin():
    project = pyproject()
    required = [Requirement(d) for d in project["dependencies"]]
    optional = [Requirement(d) for extra in project["optional-dependencies"].values() for d in extra]
    ranges = {r.name.lower(): r.specifier for r in required + optional}
    for version in SUPPORTED:
        pins = {r.name.lower(): r for r in active(version)}
        missing = {r.name.lower() for r in required} - set(pins)
        assert not missing, f"pyproject.toml needs {missing}, requirements.txt pins none for Python {version}"
        for name, pin in pins.items():
            assert name in ranges, f"{name} is pinned in requirements.txt but not declared in pyproject.toml"
            exact = next(iter(pin.specifier)).version
            assert ranges[name].contains(exact), f"{pin} (Python {version}) is outside {ranges[name]}"
