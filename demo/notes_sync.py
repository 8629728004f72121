"""Keeping the prose true: code excerpts, numbers from results files, and the figures' manifest.

``python -m demo figures`` (``demo/figures.py``) draws the figures; this module rewrites the text
around them and checks it (``--check``). Documents: the chapters ``lecture_notes/NN-*.md``, the
notes' index, and beside ``lecture_notes/`` the project ``README.md`` and ``benchmarks/README.md``.
Four kinds of marked text are kept in sync, each replaced by what it names:

* ``<!-- excerpt: solver/file.py Name.or.function -->`` followed by a ```python block: that
  function's current source;
* ``<!-- begin generated: KEY -->`` ... ``<!-- end generated -->`` and ``<!--v:KEY-->...<!--/v-->``:
  the text stored under KEY in ``lecture_notes/figures/numbers.json`` (written by the figure sections);
* ``<!--n: PATH | WHERE | COLUMN | FORMAT -->...<!--/n-->``: one value of a committed results file,
  for example ``<!--n: benchmarks/results/pareto/cases.csv | case=E=1e+06 Pa, 3840 tets, rest |
  newton_seconds | 1000*.1f -->11.4<!--/n-->``. PATH is a CSV file (WHERE: ``column=value`` pairs
  separated by ``;`` that select exactly one row) or a JSON file (WHERE empty, COLUMN a key).
  FORMAT is ``[SCALE*]SPEC``: the value times SCALE, written with the Python format SPEC or with
  ``sci`` (two significant digits, ``1.4e-2``), or ``text``: the value as the file has it (a name);
* ``<!-- begin include: PATH -->`` ... ``<!-- end include -->``: the whole text of a results file
  (the benchmarks' ``summary.md`` tables).

A number typed by hand into a marked place is therefore either rewritten or reported, so a table
and the sentence quoting it cannot disagree.

Every figure run also records, per section, a hash of what its figures are drawn from in
``lecture_notes/figures/manifest.json``: the section's own code in ``demo/figures.py`` (with the
helpers and constants it names), the solver, the demo modules that build and draw scenes, the assets,
and the parameters (``--size``, ``--full``), plus a hash of each PNG it wrote. ``--check`` recomputes
them, so a figure whose code, solver or parameters changed since it was drawn (or a PNG replaced by
hand) is reported as stale. Hashing the inputs rather than comparing pixels keeps the check exact on
any machine: floating point and threading differ between CPUs, the hash of the source does not.
"""
import ast
import csv
import functools
import hashlib
import io
import json
import os
import re
import textwrap
import tokenize
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
NOTES = REPO_ROOT / "lecture_notes"
FIGURES = NOTES / "figures"
NUMBERS = "numbers.json"
MANIFEST = "manifest.json"
SECTIONS_FILE = "demo/figures.py"
# What every section's figures are drawn from, besides the section's own code in SECTIONS_FILE.
DEPENDENCIES = ("solver/**/*.py", "demo/scenes.py", "demo/runner.py", "demo/compose.py", "demo/render.py",
                "demo/colors.py", "assets/*")

GENERATED = re.compile(r"(<!-- begin generated: (?P<key>[\w.\-]+) -->\n)(?P<body>.*?)(\n<!-- end generated -->)", re.S)
INLINE = re.compile(r"(<!--v:(?P<key>[\w.\-]+)-->)(?P<body>.*?)(<!--/v-->)")
EXCERPT = re.compile(r"(<!-- excerpt: (?P<path>\S+) (?P<name>[\w.]+) -->\n```python\n)(?P<body>.*?)(\n```)", re.S)
RESULT = re.compile(r"(<!--n:(?P<spec>[^>\n]*?)-->)(?P<body>.*?)(<!--/n-->)")
INCLUDE = re.compile(r"(<!-- begin include: (?P<path>\S+) -->\n)(?P<body>.*?)\n?(<!-- end include -->)", re.S)
SOLUTION_MARKER = re.compile(r"^[ \t]*# (BEGIN|END) SOLUTION\b.*$")


# ---------------------------------------------------------------------------------------------
# Code excerpts
# ---------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=32)
def _module_tree(text: str) -> ast.Module:
    """The syntax tree of a Python file's text, parsed once for all the excerpts quoted from it (read only)."""
    return ast.parse(text)


def function_source(path: Path, name: str) -> str:
    """Dedented source of `name` ("function" or "Class.method") in the Python file `path`, decorators
    included, without the homework's solution markers (a region that ends the function would otherwise
    be quoted without its END line)."""
    text = path.read_text(encoding="utf-8")
    node = _module_tree(text)
    for part in name.split("."):
        matches = [child for child in ast.iter_child_nodes(node)
                   if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and child.name == part]
        if not matches:
            raise KeyError(f"{name} not found in {path}")
        node = matches[0]
    first = min([node.lineno] + [d.lineno for d in node.decorator_list])
    lines = [line for line in text.splitlines()[first - 1:node.end_lineno] if not SOLUTION_MARKER.match(line)]
    return textwrap.dedent("\n".join(lines)).rstrip()


def refresh_excerpts(text: str, root: Path = REPO_ROOT) -> str:
    def replace(match):
        return match.group(1) + function_source(root / match["path"], match["name"]) + match.group(5)

    return EXCERPT.sub(replace, text)


# ---------------------------------------------------------------------------------------------
# Numbers from numbers.json and from results files
# ---------------------------------------------------------------------------------------------
class ResultError(Exception):
    """A results marker that names no single value: the message says which and why."""


def _format(value: float, fmt: str) -> str:
    scale, _, spec = fmt.rpartition("*")
    value = value * float(scale) if scale else value
    if spec == "sci":
        mantissa, exponent = f"{value:.1e}".split("e")
        return f"{mantissa}e{int(exponent)}"
    return format(value, spec)


def result_value(spec: str, root: Path = REPO_ROOT) -> str:
    """The text a ``<!--n: PATH | WHERE | COLUMN | FORMAT -->`` marker stands for (module docstring)."""
    parts = [p.strip() for p in spec.split("|")]
    if len(parts) != 4:
        raise ResultError(f"marker {spec.strip()!r} needs four fields: PATH | WHERE | COLUMN | FORMAT")
    path, where, column, fmt = parts
    file = root / path
    if not file.is_file():
        raise ResultError(f"results file {path} does not exist")
    if file.suffix == ".json":
        data = json.loads(file.read_text(encoding="utf-8"))
        if column not in data:
            raise ResultError(f"{path} has no key {column!r}")
        raw = data[column]
    else:
        conditions = [c.split("=", 1) for c in where.split(";") if c.strip()]
        if any(len(c) != 2 for c in conditions):
            raise ResultError(f"{path}: WHERE {where!r} must be column=value pairs separated by ';'")
        with file.open(newline="", encoding="utf-8") as handle:
            rows = [row for row in csv.DictReader(handle)
                    if all(row.get(k.strip()) == v.strip() for k, v in conditions)]
        if len(rows) != 1:
            raise ResultError(f"{path}: {len(rows)} rows match {where!r}, not one")
        if not rows[0].get(column):
            raise ResultError(f"{path}: no value in column {column!r} of the row {where!r}")
        raw = rows[0][column]
    if fmt == "text":
        return str(raw)
    try:
        return _format(float(raw), fmt)
    except ValueError:
        raise ResultError(f"{path}: {column} = {raw!r} cannot be written with format {fmt!r}") from None


def included_text(path: str, folder: Path, root: Path = REPO_ROOT) -> str:
    """The text of results file `path` (relative to `root`) as it appears in a document in `folder`:
    its relative links and images rebased so that they still point at the files beside it."""
    source = root / path

    def rebase(match):
        target = match["target"]
        if re.match(r"[a-z]+:|/|#", target):
            return match.group(0)
        return f"]({os.path.relpath(source.parent / target, folder)})"

    return re.sub(r"\]\((?P<target>[^)\s]+)\)", rebase, source.read_text(encoding="utf-8").strip())


def fill_generated(text: str, numbers: dict, root: Path = REPO_ROOT, folder: Path = NOTES) -> str:
    """Replace every generated block, inline value, results number and include whose source is known;
    `folder` is where the document lies (for the links of included files)."""
    def from_numbers(match):
        key = match["key"]
        return match.group(1) + numbers[key] + match.group(4) if key in numbers else match.group(0)

    def from_results(match):
        try:
            return match.group(1) + result_value(match["spec"], root) + match.group(4)
        except ResultError:
            return match.group(0)

    def include(match):
        if not (root / match["path"]).is_file():
            return match.group(0)
        return match.group(1) + included_text(match["path"], folder, root) + "\n" + match.group(4)

    text = INLINE.sub(from_numbers, GENERATED.sub(from_numbers, text))
    return INCLUDE.sub(include, RESULT.sub(from_results, text))


# ---------------------------------------------------------------------------------------------
# Documents
# ---------------------------------------------------------------------------------------------
def chapters(notes: Path = NOTES):
    return sorted(notes.glob("[0-9][0-9]-*.md"))


def documents(notes: Path = NOTES):
    """Every file kept in sync: the chapters, the notes' index, and the READMEs of the project that
    holds `notes` (when there are)."""
    extra = [notes / "README.md", notes.parent / "README.md", notes.parent / "benchmarks" / "README.md"]
    return chapters(notes) + [p for p in extra if p.is_file()]


def _name(path: Path, notes: Path) -> str:
    return path.name if path.parent == notes else path.relative_to(notes.parent).as_posix()


def update_notes(numbers: dict, notes: Path = NOTES, root: Path = REPO_ROOT) -> list:
    """Rewrite the marked text of every document; returns the files that changed."""
    changed = []
    for path in documents(notes):
        text = path.read_text(encoding="utf-8")
        new = refresh_excerpts(fill_generated(text, numbers, root, path.parent), root)
        if new != text:
            path.write_text(new, encoding="utf-8")
            changed.append(path)
    return changed


def stale(numbers: dict, notes: Path = NOTES, root: Path = REPO_ROOT) -> list:
    """Problems that `update_notes` would fix, or that it cannot: one line each."""
    problems = []
    for path in documents(notes):
        name, text = _name(path, notes), path.read_text(encoding="utf-8")
        for match in list(GENERATED.finditer(text)) + list(INLINE.finditer(text)):
            if match["key"] not in numbers:
                problems.append(f"{name}: no number {match['key']!r} in {NUMBERS}; run python -m demo figures")
            elif numbers[match["key"]] != match["body"]:
                problems.append(f"{name}: {match['key']} differs from {NUMBERS}; run python -m demo figures")
        for match in RESULT.finditer(text):
            try:
                value = result_value(match["spec"], root)
            except ResultError as e:
                problems.append(f"{name}: {e}")
                continue
            if value != match["body"]:
                problems.append(f"{name}: {match['body']!r} should be {value!r} ({match['spec'].strip()}); "
                                f"run python -m demo figures --only excerpts")
        for match in INCLUDE.finditer(text):
            source = root / match["path"]
            if not source.is_file():
                problems.append(f"{name}: included results file {match['path']} does not exist")
            elif included_text(match["path"], path.parent, root) != match["body"]:
                problems.append(f"{name}: the copy of {match['path']} differs from the file; "
                                f"run python -m demo figures --only excerpts")
        for match in EXCERPT.finditer(text):
            try:
                source = function_source(root / match["path"], match["name"])
            except (OSError, KeyError, SyntaxError) as e:
                problems.append(f"{name}: excerpt {match['path']} {match['name']}: {e}")
                continue
            if source != match["body"]:
                problems.append(f"{name}: excerpt of {match['path']} {match['name']} no longer matches the "
                                f"source; run python -m demo figures --only excerpts")
    return problems


def figure_links(notes: Path = NOTES):
    links = set()
    for path in chapters(notes):
        links.update(re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", path.read_text(encoding="utf-8")))
    return sorted(links)


# ---------------------------------------------------------------------------------------------
# Figures: what each was drawn from (manifest.json)
# ---------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1024)
def _code_text(text: str) -> str:
    """Python source without comments, trailing spaces and blank lines: a comment edit is not a new figure.
    Cached by text: a check of every section reads each solver file once per section."""
    try:
        comments = [token.start for token in tokenize.generate_tokens(io.StringIO(text).readline)
                    if token.type == tokenize.COMMENT]
    except (tokenize.TokenError, SyntaxError):
        comments = []
    lines = text.splitlines()
    for row, col in comments:
        lines[row - 1] = lines[row - 1][:col]
    return "\n".join(line.rstrip() for line in lines if line.strip())


def _section_code(name: str, root: Path = REPO_ROOT) -> str:
    """The source of section `name` in SECTIONS_FILE with every module-level helper and constant it
    names, directly or through those helpers."""
    return _section_code_in(name, (root / SECTIONS_FILE).read_text(encoding="utf-8"))


@functools.lru_cache(maxsize=256)
def _section_code_in(name: str, text: str) -> str:
    definitions = {}
    for node in ast.parse(text).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            definitions[node.name] = node
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                if isinstance(target, ast.Name):
                    definitions[target.id] = node
    wanted, todo = [], [f"section_{name}"]
    while todo:
        current = todo.pop()
        if current in wanted or current not in definitions:
            continue
        wanted.append(current)
        todo += [n.id for n in ast.walk(definitions[current]) if isinstance(n, ast.Name)]
    lines = text.splitlines(keepends=True)
    return "\n\n".join(_code_text(_segment(lines, definitions[n])) for n in sorted(wanted))


def _segment(lines: list, node: ast.stmt) -> str:
    """`ast.get_source_segment` of a statement from its file's lines (split once: that function splits the
    whole text at every call)."""
    first, last = node.lineno - 1, node.end_lineno - 1
    if first == last:
        return lines[first].encode()[node.col_offset:node.end_col_offset].decode()
    head = lines[first].encode()[node.col_offset:].decode()
    tail = lines[last].encode()[:node.end_col_offset].decode()
    return "".join([head, *lines[first + 1:last], tail])


def section_inputs(name: str, size, full: bool, root: Path = REPO_ROOT) -> str:
    """A hash of everything section `name` draws its figures from (module docstring)."""
    digest = hashlib.sha256()
    digest.update(f"section {name}; size {size[0]}x{size[1]}; full {bool(full)}\n".encode())
    digest.update(_section_code(name, root).encode())
    for pattern in DEPENDENCIES:
        for path in sorted(root.glob(pattern)):
            if not path.is_file():
                continue
            data = path.read_bytes()
            if path.suffix == ".py":
                data = _code_text(data.decode("utf-8")).encode()
            digest.update(f"\n{path.relative_to(root).as_posix()}\n".encode())
            digest.update(data)
    return digest.hexdigest()


def _file_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def snapshot(folder: Path) -> dict:
    """{PNG name: modification time} of `folder`, to tell which PNGs a section then wrote."""
    return {p.name: p.stat().st_mtime_ns for p in folder.glob("*.png")}


def record_section(out: Path, name: str, before: dict, size, full: bool, root: Path = REPO_ROOT) -> None:
    """Note in out/manifest.json what section `name` was drawn from and the PNGs it wrote since `before`."""
    path = out / MANIFEST
    manifest = json.loads(path.read_text()) if path.exists() else {}
    drawn = sorted(n for n, stamp in snapshot(out).items() if before.get(n) != stamp)
    manifest[name] = {"inputs": section_inputs(name, size, full, root), "size": f"{size[0]}x{size[1]}",
                      "full": bool(full), "figures": {n: _file_hash(out / n) for n in drawn}}
    path.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")


def stale_figures(sections, out: Path = FIGURES, notes: Path = NOTES, size=(960, 420), full: bool = False,
                  root: Path = REPO_ROOT, links: bool = True) -> list:
    """Figures of the named `sections` that no longer match what `python -m demo figures` would draw
    now and, with `links` (`sections` being all of them), figures shown in the notes that are missing or
    that no section draws: one line each."""
    path = out / MANIFEST
    if not path.exists():
        return [f"no {MANIFEST} in {out.name}/: the figures' origin is unknown; run python -m demo figures"]
    manifest = json.loads(path.read_text())
    problems, drawn = [], set()
    for name in sections:
        entry = manifest.get(name)
        if entry is None:
            problems.append(f"section {name} has never been drawn; run python -m demo figures --only {name}")
            continue
        drawn.update(entry["figures"])
        if entry["inputs"] != section_inputs(name, size, full, root):
            was = f"drawn at size {entry['size']}{' with --full' if entry['full'] else ''}"
            problems.append(f"section {name}: its code, the solver, the scenes or the parameters changed since its "
                            f"figures were {was}; run python -m demo figures --only {name}")
        for figure, digest in sorted(entry["figures"].items()):
            if not (out / figure).exists() or _file_hash(out / figure) != digest:
                problems.append(f"{figure} is not the picture section {name} drew; "
                                f"run python -m demo figures --only {name}")
    for link in figure_links(notes) if links else ():
        if not (notes / link).exists():
            problems.append(f"missing figure {link}; run python -m demo figures")
        elif (notes / link).parent.resolve() == out.resolve() and Path(link).name not in drawn:
            problems.append(f"{link} is shown in the notes but drawn by no section")
    return problems
