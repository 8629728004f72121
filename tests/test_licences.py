"""The licence files: LICENSES-dependencies.md agrees with the requirements files and with the installed
packages' metadata, no package of the default set conflicts with the MIT licence, and CITATION.cff has
the keys the Citation File Format requires."""
import importlib.metadata
import importlib.util
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _load_tool():
    spec = importlib.util.spec_from_file_location("licences", os.path.join(ROOT, "tools", "licences.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


licences = _load_tool()


def _table(heading):
    """Rows (lists of cells) of the markdown table under `## heading` in LICENSES-dependencies.md."""
    with open(os.path.join(ROOT, licences.OUTPUT)) as fh:
        text = fh.read()
    section = text.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    lines = [line for line in section.splitlines() if line.startswith("|")][2:]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]


def test_the_list_has_every_pinned_package_with_its_pinned_versions_and_nothing_else():
    pins = licences.read_pins()
    expected = {}
    for group, package, version, marker in pins:
        expected.setdefault((group, package), []).append(f"{version} ({marker})" if marker else version)
    listed = {(row[0], row[1]): row[2].split("; ") for row in _table("Packages")}
    assert listed == expected
    assert ("cholmod", "cvxopt") in listed and not any(p == "cvxopt" for g, p in listed if g == "default")


def test_licences_agree_with_the_metadata_of_the_installed_pinned_versions():
    """For every listed package installed at a pinned version, the licence the tool reads now is the one
    in the file (the file is not stale); packages not installed here (optional sets) are skipped."""
    checked = 0
    for group, package, versions, licence, source, _ in _table("Packages"):
        try:
            dist = importlib.metadata.distribution(package)
        except importlib.metadata.PackageNotFoundError:
            continue
        if not any(v.split(" (")[0] == dist.version for v in versions.split("; ")):
            continue
        read, how = licences.metadata_licence(dist)
        if package in licences.OVERRIDES:
            read, how = licences.OVERRIDES[package][0], "override"
        assert (read, how) == (licence, source), package
        checked += 1
    assert checked >= 10        # the default set is installed wherever the tests run


@pytest.mark.parametrize("licence, how, conflict", [
    ("MIT", "package", False),
    ("MPL-2.0 AND MIT", "package", False),
    ("GPL-3.0-or-later", "package", True),
    ("AGPL-3.0-only", "package", True),
    ("BSD-3-Clause AND GPL-2.0-or-later", "package", True),
    ("LGPL-2.1-or-later", "package", True),
    ("LGPL-2.1-or-later", licences.SHARED_LIBRARY, False),
    ("GPL-2.0-or-later", licences.SHARED_LIBRARY, True),
    ("GPL-3.0-or-later WITH GCC-exception-3.1", licences.SHARED_LIBRARY, False),
    ("FTL OR GPL-2.0-or-later", licences.SHARED_LIBRARY, False),
    ("GPL-3.0-or-later", licences.PROGRAM, False),
])
def test_the_conflict_rule(licence, how, conflict):
    assert licences.conflicts(licence, how) is conflict


def test_no_package_or_bundled_component_of_the_default_set_conflicts_with_mit():
    packages = [row for row in _table("Packages") + _table("Installed with them") if row[0] == "default"]
    components = [row for row in _table("Native code bundled in the wheels") if row[0] == "default"]
    assert packages and components and "rich" in [row[1] for row in packages]     # taichi's requirement
    assert [row[1] for row in packages if licences.conflicts(row[3])] == []
    assert [row[2] for row in components if licences.conflicts(row[3], row[4])] == []
    lgpl = {row[2] for row in components if "LGPL" in row[3]}
    assert all(row[4] == licences.SHARED_LIBRARY for row in components if "LGPL" in row[3])
    assert lgpl == {"libquadmath"}      # named in the notes of LICENSES-dependencies.md


def test_the_optional_cholmod_set_is_what_carries_gpl_code():
    rows = _table("Packages") + _table("Installed with them")
    gpl = {row[1] for row in rows if licences.conflicts(row[3])}
    assert gpl == {"cvxopt", "cholespy"}
    assert all(row[0] == "cholmod" for row in rows if row[1] in gpl)


def test_citation_cff_has_the_required_keys_and_cites_vbd():
    with open(os.path.join(ROOT, "CITATION.cff")) as fh:
        text = fh.read()
    top = {m.group(1) for m in re.finditer(r"^([a-z-]+):", text, flags=re.MULTILINE)}
    assert {"cff-version", "message", "title", "authors", "license", "preferred-citation", "references"} <= top
    assert re.search(r"^cff-version: 1\.2\.0$", text, flags=re.MULTILINE)
    assert re.search(r"^license: MIT$", text, flags=re.MULTILINE)
    dois = re.findall(r"^\s+doi: (\S+)$", text, flags=re.MULTILINE)
    assert "10.1145/3658179" in dois and all(re.fullmatch(r"10\.\d{4,}/\S+", d) for d in dois)


def test_licence_files_name_the_licences():
    with open(os.path.join(ROOT, "LICENSE")) as fh:
        assert fh.readline().strip() == "MIT License"
    with open(os.path.join(ROOT, "pyproject.toml")) as fh:
        assert re.search(r'^license = "MIT"$', fh.read(), flags=re.MULTILINE)
    with open(os.path.join(ROOT, "lecture_notes", "README.md")) as fh:
        assert "CC BY 4.0" in fh.read()


def test_pyproject_extras_declare_the_optional_sets():
    tomllib = pytest.importorskip("tomllib", reason="tomllib is in the standard library from Python 3.11")
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as fh:
        project = tomllib.load(fh)["project"]
    for group in ("mesh", "cholmod"):
        declared = {licences.canonical(re.split(r"[<>=!~ ;\[]", d, maxsplit=1)[0])
                    for d in project["optional-dependencies"][group]}
        assert declared == {package for g, package, _, _ in licences.read_pins() if g == group}, group
    assert "cvxopt" not in " ".join(project["dependencies"])
