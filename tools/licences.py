"""Write LICENSES-dependencies.md: every package pinned in the requirements files and every package they
pull in, with version and licence read from the installed packages' metadata, and the native libraries
and programs their wheels bundle. Standard library only.

    python tools/licences.py                      # from the packages installed in this environment
    python tools/licences.py --path WHEEL ...     # also read packages not installed, from their wheels
    python tools/licences.py --check              # change nothing; exit 1 if the file is out of date

A package's licence is its entry of OVERRIDES (with the reason) where its metadata is missing, a whole
licence text, too vague ("BSD License") or wrong; otherwise, in this order, its `License-Expression`
(PEP 639), its `License` field when that is a licence name or expression, or its "License ::" classifiers. The MIT code of this project may
depend on permissive packages only (`conflicts`): GPL and AGPL code stay out of the default set
(requirements.txt); LGPL code and GPL code under the GCC runtime exception only as shared libraries that
the Python extensions load at run time; a GPL program only as a separate executable.
"""
import argparse
import importlib.metadata
import os
import re
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUTPUT = "LICENSES-dependencies.md"

# requirements file -> the set it defines (README "Install").
REQUIREMENT_SETS = {"requirements.txt": "default", "requirements-mesh.txt": "mesh",
                    "requirements-cholmod.txt": "cholmod"}

# Short `License` fields -> SPDX identifiers.
SPDX_NAMES = {"apache 2.0": "Apache-2.0"}
SPDX_EXPRESSION = re.compile(r"[A-Za-z0-9.+-]+( (AND|OR|WITH) [A-Za-z0-9.+-]+)*")
CLASSIFIERS = {"License :: OSI Approved :: MIT License": "MIT",
               "License :: OSI Approved :: Apache Software License": "Apache-2.0",
               "License :: OSI Approved :: Mozilla Public License 2.0 (MPL 2.0)": "MPL-2.0"}

# package -> (licence, why the metadata is not used as it is)
OVERRIDES = {
    "colorama": ("BSD-3-Clause", "no `License` field; its classifier only says 'BSD License'; LICENSE.txt is "
                 "BSD-3-Clause"),
    "contourpy": ("BSD-3-Clause", "`License` holds the whole text, titled 'BSD 3-Clause License'; its "
                  "classifier only says 'BSD License'"),
    "cycler": ("BSD-3-Clause", "`License` holds the copyright line; its classifier only says 'BSD License'; "
               "LICENSE is BSD-3-Clause"),
    "kiwisolver": ("BSD-3-Clause", "`License` holds the whole text, the Modified BSD License; its classifier "
                   "only says 'BSD License'"),
    "numpy": ("BSD-3-Clause", "`License` holds the whole licence text; its classifier only says 'BSD "
              "License'; the text is BSD-3-Clause"),
    "scipy": ("BSD-3-Clause", "`License` holds the whole licence text; its classifier only says 'BSD "
              "License'; the text is BSD-3-Clause"),
    "matplotlib": ("LicenseRef-Matplotlib", "`License` holds the whole text: the Matplotlib License, "
                   "permissive, based on the PSF licence (classifier 'Python Software Foundation License')"),
    "cvxopt": ("GPL-3.0-or-later", "`License` says only 'CVXOPT version 1.3'; its LICENSE file is GPL-3 or "
               "later"),
    "cholespy": ("BSD-3-Clause AND GPL-2.0-or-later", "metadata and licence file say BSD-3-Clause (the "
                 "wrapper), but its extension module links CHOLMOD statically, Supernodal module (GPL-2.0 or "
                 "later) included: `nm` lists cholmod_super_numeric in _cholespy_core"),
}

# Native libraries bundled in wheels (`<package>.libs/`), by library name, and bundled programs.
LIBRARIES = {
    "libgfortran": "GPL-3.0-or-later WITH GCC-exception-3.1",
    "libgomp": "GPL-3.0-or-later WITH GCC-exception-3.1",
    "libquadmath": "LGPL-2.1-or-later",
    "libopenblas": "BSD-3-Clause", "libopenblas64_p": "BSD-3-Clause", "libopenblasp": "BSD-3-Clause",
    "libblas": "BSD-3-Clause", "liblapack": "BSD-3-Clause", "libsatlas": "BSD-3-Clause",
    "libgmp": "LGPL-3.0-or-later OR GPL-2.0-or-later",
    "libXau": "MIT", "libxcb": "MIT", "libbrotlicommon": "MIT", "libbrotlidec": "MIT",
    "libfreetype": "FTL OR GPL-2.0-or-later", "libharfbuzz": "MIT", "libjpeg": "IJG AND BSD-3-Clause AND Zlib",
    "liblcms2": "MIT", "liblzma": "0BSD", "libopenjp2": "BSD-2-Clause", "libpng16": "libpng-2.0",
    "libsharpyuv": "BSD-3-Clause", "libwebp": "BSD-3-Clause", "libwebpdemux": "BSD-3-Clause",
    "libwebpmux": "BSD-3-Clause", "libtiff": "libtiff",
    "libamd": "BSD-3-Clause", "libcamd": "BSD-3-Clause", "libccolamd": "BSD-3-Clause", "libcolamd": "BSD-3-Clause",
    "libsuitesparseconfig": "BSD-3-Clause", "libcholmod": "LGPL-2.1-or-later AND GPL-2.0-or-later",
    "libumfpack": "GPL-2.0-or-later", "libfftw3": "GPL-2.0-or-later", "libglpk": "GPL-3.0-or-later",
    "libgsl": "GPL-3.0-or-later", "libdsdp": "LicenseRef-DSDP",
}
PROGRAMS = {"ffmpeg": "GPL-3.0-or-later"}
SHARED_LIBRARY, PROGRAM = "shared library", "separate program"

NOTES = """\
- **imageio-ffmpeg** ships a static `ffmpeg` executable (4.2.2, from johnvansickle.com), configured with
  `--enable-gpl --enable-version3`, so the program is GPL-3.0-or-later. imageio runs it as a separate
  process and talks to it through pipes and command-line arguments (the demo's video export only); no
  ffmpeg code is linked into a Python process or into this project's code, so the program's licence does
  not extend to them (the GPL's "aggregate" case). Whoever redistributes the binary owes its source
  offer; `pip` downloads it from PyPI, this repository does not contain it.
- **LGPL in the default set**: `libquadmath` (LGPL-2.1-or-later), bundled by the numpy and scipy wheels
  as a shared library that their extension modules load at run time, so it can be replaced; that is what
  the LGPL asks.
- **GCC runtime libraries** (`libgfortran`, `libgomp`): GPL-3.0 with the GCC Runtime Library Exception,
  which lets code compiled with GCC link them under any licence.
- **cholespy** is not in the default set: its wheel carries CHOLMOD's GPL Supernodal module statically
  linked (its metadata says BSD-3-Clause, for the wrapper only), and it is never the fastest solver here.
- **cvxopt** (GPL-3.0-or-later, with CHOLMOD, UMFPACK, FFTW, GLPK and GSL, all GPL) is the optional
  `cholmod` set: installed by choice, for speed (README, "Licence"); without it the code runs on
  qdldl (Apache-2.0) and scipy's SuperLU (BSD-3-Clause).
"""


def canonical(name: str) -> str:
    """PEP 503 normalised package name."""
    return re.sub(r"[-_.]+", "-", name).lower()


def read_pins(root: str = ROOT) -> list:
    """[(set, package, version, marker)] for every `name==version` line of the requirements files;
    `-r` includes and the interpreter guard (`name @ url`) are not packages."""
    pins = []
    for filename, group in REQUIREMENT_SETS.items():
        with open(os.path.join(root, filename)) as fh:
            for line in fh:
                line = line.split("#", 1)[0].strip() if not line.lstrip().startswith("#") else ""
                if not line or line.startswith("-r") or " @ " in line:
                    continue
                requirement, _, marker = line.partition(";")
                name, sep, version = requirement.partition("==")
                if not sep:
                    raise SystemExit(f"{filename}: '{line}' is not pinned; pin it as name==version")
                pins.append((group, canonical(name.strip()), version.strip(), marker.strip()))
    return pins


def metadata_licence(dist) -> tuple:
    """(licence, source) of an installed distribution, or (None, why) when its metadata is ambiguous."""
    meta = dist.metadata
    if meta.get("License-Expression"):
        return meta["License-Expression"].strip(), "License-Expression"
    field = (meta.get("License") or "").strip()
    if field.lower() in SPDX_NAMES:
        return SPDX_NAMES[field.lower()], "License"
    if SPDX_EXPRESSION.fullmatch(field):
        return field, "License"
    classifiers = [CLASSIFIERS.get(c) for c in meta.get_all("Classifier") or [] if c.startswith("License ::")]
    if classifiers and all(classifiers):
        return " AND ".join(sorted(set(classifiers))), "classifier"
    return None, "ambiguous metadata"


def distributions(paths: list) -> dict:
    """canonical name -> distribution, installed ones first, then those in `paths` (wheels or folders)."""
    found = {}
    for dist in list(importlib.metadata.distributions()) + list(importlib.metadata.distributions(path=paths)):
        found.setdefault(canonical(dist.metadata["Name"]), dist)
    return found


def bundled(dist) -> list:
    """[(component, licence, how it is used)]: the native libraries in the wheel's `<name>.libs/` and
    the programs it ships."""
    out = []
    for file in dist.files or []:
        parts = file.parts
        base = parts[-1]
        if len(parts) == 2 and parts[0].endswith(".libs") and ".so" in base:
            library = base.split("-")[0]      # auditwheel names them <library>-<hash>.so.<version>
            out.append((library, LIBRARIES.get(library), SHARED_LIBRARY))
        elif "binaries" in parts and base.split("-")[0] in PROGRAMS:
            out.append((base, PROGRAMS[base.split("-")[0]], PROGRAM))
    return sorted(set(out))


def conflicts(licence: str, how: str = "package") -> bool:
    """Whether code under `licence` (an SPDX expression without parentheses) used as `how` ("package":
    imported into the Python process; SHARED_LIBRARY; PROGRAM) conflicts with MIT code that must stay
    usable under MIT: some alternative of the OR must be free of GPL/AGPL terms, allowing LGPL and the GCC
    runtime exception for shared libraries and any GPL for a separate program."""
    def term_ok(term):
        if "GPL" not in term:
            return True
        if how == PROGRAM:
            return True
        if how == SHARED_LIBRARY:
            return term.startswith("LGPL") or "WITH GCC-exception" in term
        return False
    return not any(all(term_ok(t.strip()) for t in alternative.split(" AND "))
                   for alternative in licence.split(" OR "))


def licence_of(package: str, dist) -> tuple:
    """(licence, source) of a distribution: an override, else its metadata. Raises SystemExit when the
    metadata is ambiguous and there is no override."""
    if package in OVERRIDES:
        return OVERRIDES[package][0], "override"
    licence, source = metadata_licence(dist)
    if licence is None:
        raise SystemExit(f"{package}: {source}; add it to OVERRIDES in tools/licences.py with the reason")
    return licence, source


def requirements_of(dist) -> list:
    """Canonical names of what `dist` requires outside its extras (markers for other Pythons or systems
    are not evaluated: such a requirement counts when it is installed)."""
    out = []
    for line in dist.requires or []:
        name, _, marker = line.partition(";")
        if "extra ==" not in marker:
            out.append(canonical(re.match(r"[A-Za-z0-9._-]+", name.strip()).group(0)))
    return out


def pulled_in(roots: list, dists: dict, known: set) -> dict:
    """package -> the packages that require it: every installed package that `roots` require, directly or
    through each other, and that is not in `known`."""
    found, queue = {}, list(roots)
    while queue:
        parent = queue.pop()
        for child in requirements_of(dists[parent]):
            if child in dists and child not in known and child not in roots:
                if child not in found:
                    queue.append(child)
                found.setdefault(child, set()).add(parent)
    return found


def render(paths: list = ()) -> str:
    """The text of LICENSES-dependencies.md. Raises SystemExit naming a package whose metadata cannot be
    read or is ambiguous without an override, and a bundled library without a known licence."""
    pins = read_pins()
    dists = distributions(list(paths))
    rows, indirect, components = [], [], []
    known = set()
    for group in REQUIREMENT_SETS.values():
        pinned = sorted({n for g, n, _, _ in pins if g == group})
        missing = [n for n in pinned if n not in dists]
        if missing:
            raise SystemExit(f"{', '.join(missing)} not installed: install the {group} set, or pass its wheels "
                             "with --path")
        for package in pinned:
            dist = dists[package]
            versions = [v for g, n, v, m in pins if (g, n) == (group, package)]
            listed = "; ".join(f"{v} ({m})" if m else v for g, n, v, m in pins if (g, n) == (group, package))
            read = dist.version if dist.version in versions else f"{dist.version} (not a pinned version)"
            rows.append(f"| {group} | {package} | {listed} | " + " | ".join(licence_of(package, dist)) + f" | {read} |")
        known |= set(pinned)
        extra = pulled_in(pinned, dists, known)
        for package in sorted(extra):
            dist = dists[package]
            indirect.append(f"| {group} | {package} | {dist.version} | " + " | ".join(licence_of(package, dist))
                            + f" | {', '.join(sorted(extra[package]))} |")
        known |= set(extra)
        for package in pinned + sorted(extra):
            for component, component_licence, how in bundled(dists[package]):
                if component_licence is None:
                    raise SystemExit(f"{package} bundles {component}: add its licence to LIBRARIES in "
                                     "tools/licences.py")
                components.append(f"| {group} | {package} | {component} | {component_licence} | {how} |")
    reasons = [f"| {package} | {licence} | {why} |" for package, (licence, why) in sorted(OVERRIDES.items())]
    return "\n".join([
        "# Licences of the dependencies",
        "",
        "Generated by `python tools/licences.py` from the installed packages' metadata; do not edit by hand.",
        "`tests/test_licences.py` checks it against the requirements files and the licence rules. This",
        "project's code is MIT (`LICENSE`); sets: `default` = `requirements.txt`, `mesh` =",
        "`requirements-mesh.txt`, `cholmod` = `requirements-cholmod.txt` (each optional set adds to the default).",
        "",
        "## Packages",
        "",
        "| set | package | pinned version | licence | read from | metadata of version |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
        "## Installed with them",
        "",
        "What the pinned packages require, as installed where this file was generated (a set lists what it",
        "adds to the sets before it).",
        "",
        "| set | package | version | licence | read from | required by |",
        "|---|---|---|---|---|---|",
        *indirect,
        "",
        "## Native code bundled in the wheels",
        "",
        "| set | package | component | licence | used as |",
        "|---|---|---|---|---|",
        *components,
        "",
        "## Where the metadata is not used as it is",
        "",
        "| package | licence | reason |",
        "|---|---|---|",
        *reasons,
        "",
        "## Notes",
        "",
        NOTES,
    ])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--path", nargs="*", default=[], help="wheels or folders to read packages not installed from")
    p.add_argument("--out", default=os.path.join(ROOT, OUTPUT), help="file to write")
    p.add_argument("--check", action="store_true", help="change nothing; exit 1 if --out is out of date")
    args = p.parse_args(argv)
    try:
        text = render(args.path)
    except SystemExit as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if args.check:
        with open(args.out) as fh:
            current = fh.read()
        if current != text:
            print(f"{args.out} is out of date: run python tools/licences.py", file=sys.stderr)
            return 1
        return 0
    with open(args.out, "w") as fh:
        fh.write(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
