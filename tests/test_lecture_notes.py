"""The lecture notes stay true to the code: excerpts, generated numbers, figures, math."""
import json
import re
import shutil
from pathlib import Path

import pytest

from demo import figures, notes_sync
from demo.errors import DemoError

REPO = Path(__file__).resolve().parent.parent
NOTES = REPO / "lecture_notes"
CHAPTERS = ["01-implicit-euler.md", "02-newton.md", "03-coordinate-descent.md", "04-parallelism.md",
            "05-information-propagation.md", "06-what-helps.md", "07-global-channel.md",
            "08-contact.md"]


def numbers():
    return json.loads((NOTES / "figures" / notes_sync.NUMBERS).read_text())


def test_chapters_follow_the_lecture_order():
    assert [p.name for p in notes_sync.chapters()] == CHAPTERS
    index = (NOTES / "README.md").read_text()
    for number, name in enumerate(CHAPTERS, start=1):
        assert (NOTES / name).read_text().startswith(f"# {number}. ")
        assert f"]({name})" in index


def test_every_excerpt_matches_the_source_it_names():
    quoted = set()
    for path in notes_sync.chapters():
        text = path.read_text()
        assert text.count("<!-- excerpt:") == len(notes_sync.EXCERPT.findall(text)), \
            f"{path.name}: an excerpt marker is not followed by a ```python block"
        for match in notes_sync.EXCERPT.finditer(text):
            source = notes_sync.function_source(REPO / match["path"], match["name"])
            assert match["body"] == source, (f"{path.name}: the excerpt of {match['path']} {match['name']} no longer "
                                             f"matches the source; run python -m demo figures --only excerpts")
            quoted.add(match["name"])
    # the homework's functions are all quoted where they are derived
    assert {"vertex_force_hessian", "_greedy", "newton_step", "chebyshev_update"} <= quoted


def test_generated_blocks_match_numbers_json():
    assert notes_sync.stale(numbers()) == []
    for path in notes_sync.chapters():
        text = path.read_text()
        assert "(run python -m demo figures)" not in text and "-->?<!--" not in text, path.name


def test_every_figure_exists_and_is_small():
    links = notes_sync.figure_links(NOTES)
    assert len(links) >= 10
    total = 0
    for link in links:
        path = NOTES / link
        assert path.exists(), f"missing {link}; run python -m demo figures"
        total += path.stat().st_size
        assert path.stat().st_size < 300_000, f"{link} is large"
    assert total < 2_500_000
    produced = {p.name for p in (NOTES / "figures").glob("*.png")}
    in_figures = {Path(link).name for link in links if Path(link).parts[0] == "figures"}
    assert produced == in_figures, "figures and notes disagree about which PNGs exist"


@pytest.mark.parametrize("name", CHAPTERS)
def test_math_delimiters_are_balanced(name):
    text = (NOTES / name).read_text()
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    assert text.count("$$") % 2 == 0
    assert text.replace("$$", "").count("$") % 2 == 0


def test_check_command_passes_on_the_repository(capsys):
    assert figures.main(["--check"]) == 0
    assert "are up to date" in capsys.readouterr().out


def test_a_changed_source_is_caught(tmp_path):
    (tmp_path / "pkg").mkdir()
    source = tmp_path / "pkg" / "mod.py"
    source.write_text("class A:\n    @staticmethod\n    def f(x):\n        return x + 1\n")
    notes = tmp_path / "notes"
    notes.mkdir()
    chapter = notes / "01-x.md"
    chapter.write_text("<!-- excerpt: pkg/mod.py A.f -->\n```python\nold\n```\n"
                       "<!-- begin generated: t -->\nold\n<!-- end generated -->\nv = <!--v:n-->1<!--/v-->\n")
    problems = notes_sync.stale({"t": "new", "n": "2"}, notes, root=tmp_path)
    assert len(problems) == 3 and any("no longer matches" in p for p in problems)
    notes_sync.update_notes({"t": "new", "n": "2"}, notes, root=tmp_path)
    text = chapter.read_text()
    assert "@staticmethod\ndef f(x):\n    return x + 1\n```" in text
    assert "<!-- begin generated: t -->\nnew\n<!-- end generated -->" in text and "<!--v:n-->2<!--/v-->" in text
    assert notes_sync.stale({"t": "new", "n": "2"}, notes, root=tmp_path) == []
    source.write_text(source.read_text().replace("x + 1", "x + 2"))
    assert any("A.f no longer matches" in p for p in notes_sync.stale({"t": "new", "n": "2"}, notes, root=tmp_path))


def _results_project(tmp_path):
    """A project with one results CSV, one summary and a chapter quoting them."""
    (tmp_path / "results").mkdir()
    (tmp_path / "results" / "runs.csv").write_text('case,method,seconds\n"bar, rest",VBD,0.01234\n'
                                                   '"bar, rest",Newton,0.5\n"bar, moving",VBD,0.02\n')
    (tmp_path / "results" / "summary.md").write_text("| a |\n|---|\n| 1 |\n\n![plot](plot.png) [web](https://x.org)\n")
    notes = tmp_path / "notes"
    notes.mkdir()
    chapter = notes / "01-x.md"
    chapter.write_text("VBD: <!--n: results/runs.csv | case=bar, rest; method=VBD | seconds | 1000*.1f -->99<!--/n--> ms, "
                       "<!--n: results/runs.csv | method=Newton | seconds | sci -->0.5<!--/n--> s.\n"
                       "<!-- begin include: results/summary.md -->\nold\n<!-- end include -->\n")
    return notes, chapter


def test_an_empty_include_is_stale_and_filled(tmp_path):
    """An include whose markers stand on adjacent lines (nothing copied yet) is reported by the check and
    filled by the update, like one holding an old copy."""
    notes, chapter = _results_project(tmp_path)
    chapter.write_text("<!-- begin include: results/summary.md -->\n<!-- end include -->\n")
    assert notes_sync.stale({}, notes, root=tmp_path) == [
        "01-x.md: the copy of results/summary.md differs from the file; run python -m demo figures --only excerpts"]
    notes_sync.update_notes({}, notes, root=tmp_path)
    assert chapter.read_text().startswith("<!-- begin include: results/summary.md -->\n| a |")
    assert notes_sync.stale({}, notes, root=tmp_path) == []


def test_numbers_from_results_files_are_checked_and_filled(tmp_path):
    notes, chapter = _results_project(tmp_path)
    problems = notes_sync.stale({}, notes, root=tmp_path)
    assert len(problems) == 3
    assert any("'99' should be '12.3'" in p for p in problems) and any("'0.5' should be '5.0e-1'" in p for p in problems)
    assert any("copy of results/summary.md differs" in p for p in problems)
    notes_sync.update_notes({}, notes, root=tmp_path)
    text = chapter.read_text()
    assert "-->12.3<!--/n--> ms" in text and "-->5.0e-1<!--/n--> s" in text
    # the included file's relative links still point at the files beside it
    assert "| 1 |\n\n![plot](../results/plot.png) [web](https://x.org)\n<!-- end include -->" in text
    assert notes_sync.stale({}, notes, root=tmp_path) == []
    # a new measurement makes the quoted number stale
    path = tmp_path / "results" / "runs.csv"
    path.write_text(path.read_text().replace("0.01234", "0.0201"))
    assert notes_sync.stale({}, notes, root=tmp_path) == [
        "01-x.md: '12.3' should be '20.1' (results/runs.csv | case=bar, rest; method=VBD | seconds | 1000*.1f); "
        "run python -m demo figures --only excerpts"]


def test_a_text_marker_quotes_the_value_as_the_file_has_it(tmp_path):
    notes, chapter = _results_project(tmp_path)
    chapter.write_text("<!--n: results/runs.csv | case=bar, moving | method | text -->Newton<!--/n-->\n")
    assert notes_sync.stale({}, notes, root=tmp_path) == [
        "01-x.md: 'Newton' should be 'VBD' (results/runs.csv | case=bar, moving | method | text); "
        "run python -m demo figures --only excerpts"]
    notes_sync.update_notes({}, notes, root=tmp_path)
    assert chapter.read_text() == "<!--n: results/runs.csv | case=bar, moving | method | text -->VBD<!--/n-->\n"


@pytest.mark.parametrize("marker, message", [
    ("<!--n: results/runs.csv | method=VBD | seconds | .2f -->1<!--/n-->", "2 rows match 'method=VBD', not one"),
    ("<!--n: results/none.csv | method=VBD | seconds | .2f -->1<!--/n-->", "results file results/none.csv does not exist"),
    ("<!--n: results/runs.csv | method=Newton | minutes | .2f -->1<!--/n-->", "no value in column 'minutes'"),
    ("<!--n: results/runs.csv | method=Newton | seconds -->1<!--/n-->", "needs four fields"),
    ("<!--n: results/runs.csv | method=Newton | case | .2f -->1<!--/n-->", "cannot be written with format"),
])
def test_a_results_marker_that_names_no_single_value_is_reported(tmp_path, marker, message):
    notes, chapter = _results_project(tmp_path)
    chapter.write_text(marker + "\n")
    problems = notes_sync.stale({}, notes, root=tmp_path)
    assert len(problems) == 1 and message in problems[0], problems
    notes_sync.update_notes({}, notes, root=tmp_path)
    assert chapter.read_text() == marker + "\n"


def test_readmes_quote_their_numbers_from_results_files():
    readme = (REPO / "README.md").read_text()
    assert len(readme.encode()) < 15_000, "the README is a user's README: under 15 KB"
    first_image = re.search(r"!\[[^\]]*\]\(([^)]+)\)", readme)
    assert first_image and readme.index(first_image.group(0)) < readme.index("## "), "a picture at the top"
    assert (REPO / first_image.group(1)).is_file()
    documents = [p.relative_to(REPO).as_posix() for p in notes_sync.documents(NOTES)]
    assert {"README.md", "benchmarks/README.md"} <= set(documents)
    assert notes_sync.RESULT.search(readme), "the README's measured numbers come from results files"
    bench = (REPO / "benchmarks" / "README.md").read_text()
    included = {m["path"] for m in notes_sync.INCLUDE.finditer(bench)}
    assert {f"benchmarks/results/{name}/summary.md" for name in ("pareto", "throughput", "newton_speed")} <= included


def test_unknown_section_is_an_error(tmp_path):
    with pytest.raises(DemoError, match="unknown section"):
        figures.main(["--only", "nope", "--out", str(tmp_path)])


def test_excerpts_only_run_touches_no_figure(tmp_path):
    notes = tmp_path / "notes"
    shutil.copytree(NOTES, notes)
    before = {p.name: p.read_bytes() for p in (notes / "figures").iterdir()}
    assert figures.main(["--only", "excerpts", "--out", str(notes / "figures"), "--notes", str(notes)]) == 0
    assert {p.name: p.read_bytes() for p in (notes / "figures").iterdir()} == before


def test_a_section_is_hashed_from_the_text_python_gives_for_each_statement():
    """The figure hashes quote each statement of the sections file as `ast.get_source_segment` would
    (from lines split once, not once per statement), also where a statement starts or ends mid-line,
    spans one line, or holds text that is more than one byte a character in UTF-8."""
    import ast

    text = "".join((REPO / notes_sync.SECTIONS_FILE).read_text(encoding="utf-8").splitlines(keepends=True)[:300])
    text = text[:text.rindex("\ndef ")]         # whole statements only
    text += '\nx = 1; y = "\u00e9\u00e9"  # two statements\nz = (1 +\n     2); w = 3\n'
    lines = text.splitlines(keepends=True)
    statements = [node for node in ast.walk(ast.parse(text)) if isinstance(node, ast.stmt)]
    assert len(statements) > 50 and any(isinstance(node, ast.FunctionDef) for node in statements)
    for node in statements:
        assert notes_sync._segment(lines, node) == ast.get_source_segment(text, node), node.lineno


def test_figures_match_what_the_command_would_draw():
    """manifest.json records a hash of every section's inputs (its code, the solver, the scenes, the
    parameters) and of each PNG; after a change to any of them, `python -m demo figures` must run again."""
    assert notes_sync.stale_figures(figures.SECTIONS) == []


def _figure_project(tmp_path):
    """A copy of what the figures are drawn from, with one fake section output recorded in a manifest."""
    root = tmp_path / "project"
    for folder in ("solver", "demo", "assets"):
        shutil.copytree(REPO / folder, root / folder, ignore=shutil.ignore_patterns("__pycache__"))
    out = root / "lecture_notes" / "figures"
    out.mkdir(parents=True)
    before = notes_sync.snapshot(out)
    (out / "propagation_01.png").write_bytes(b"a picture")
    notes_sync.record_section(out, "propagation", before, (960, 420), False, root=root)
    return root, out


def _propagation_problems(root, out, size=(960, 420)):
    return [p for p in notes_sync.stale_figures(figures.SECTIONS, out, root / "lecture_notes", size, False, root=root)
            if "propagation" in p]


def test_figure_check_catches_changed_code_parameters_and_pictures(tmp_path):
    root, out = _figure_project(tmp_path)
    assert _propagation_problems(root, out) == []
    assert _propagation_problems(root, out, size=(640, 280))              # another --size
    edits = [("demo/scenes.py", "frames=41, fps=5", "frames=41, fps=6"),     # a scene parameter
             ("demo/figures.py", "saved = (1, 5, 20, 40)", "saved = (1, 5, 20, 30)"),   # the section's own code
             ("demo/figures.py", "n_colors=256", "n_colors=255"),              # a helper the section calls
             ("solver/physics/material.py", "alpha = 1.0 + mu / lam\n", "alpha = 1.0 + 0.5 * mu / lam\n")]   # the solver
    for name, old, new in edits:
        path = root / name
        text = path.read_text()
        assert old in text, (name, old)
        path.write_text(text.replace(old, new, 1))
        problems = _propagation_problems(root, out)
        assert problems and "code, the solver, the scenes or the parameters changed" in problems[0], name
        path.write_text(text)
        assert _propagation_problems(root, out) == [], name
    # comments do not change a figure, and a section's hash ignores other sections' code
    path = root / "solver" / "physics" / "material.py"
    path.write_text(path.read_text().replace("# Taichi functions used inside", "# Taichi functions, used in"))
    path = root / "demo" / "figures.py"
    path.write_text(path.read_text().replace('rhos = (None, 0.8, 0.9, 0.95, 0.98)', 'rhos = (None, 0.9)'))
    assert _propagation_problems(root, out) == []
    (out / "propagation_01.png").write_bytes(b"another picture")           # replaced by hand
    assert any("propagation_01.png is not the picture" in p for p in _propagation_problems(root, out))


def test_check_command_fails_on_stale_figures(tmp_path, capsys):
    notes = tmp_path / "notes"
    shutil.copytree(NOTES, notes)
    manifest = json.loads((notes / "figures" / notes_sync.MANIFEST).read_text())
    manifest["sweeps"]["inputs"] = "0" * 64
    (notes / "figures" / notes_sync.MANIFEST).write_text(json.dumps(manifest))
    assert figures.main(["--check", "--out", str(notes / "figures"), "--notes", str(notes)]) == 1
    assert "section sweeps:" in capsys.readouterr().out


def test_check_honours_only(tmp_path, capsys):
    """--check returned before --only was read: '--only excerpts --check' reported every figure section and
    '--only nosuch --check' no unknown section. Now --check looks at the notes and READMEs and at the
    figures of the sections --only names (none for 'excerpts'), and an unknown section is the same error."""
    out = tmp_path / "figures"
    shutil.copytree(NOTES / "figures", out)
    manifest = json.loads((out / notes_sync.MANIFEST).read_text())
    for name, entry in manifest.items():        # every section drawn from this checkout but sweeps
        entry["inputs"] = "0" * 64 if name == "sweeps" else notes_sync.section_inputs(name, (960, 420), False)
    (out / notes_sync.MANIFEST).write_text(json.dumps(manifest))
    check = ["--check", "--out", str(out), "--notes", str(NOTES)]
    for only, code in [("excerpts", 0), ("propagation", 0), ("propagation,excerpts", 0), ("sweeps", 1), (None, 1)]:
        assert figures.main(check + (["--only", only] if only is not None else [])) == code, only
        printed = capsys.readouterr().out
        assert ("section sweeps:" in printed) == (code == 1) and printed.count("section ") == code, (only, printed)
        if only == "excerpts":
            assert "the figures of 0 section(s)" in printed, printed
    # the notes' pictures are checked against every section's figures only when every section is checked
    figures.main(["--check", "--only", "propagation"])
    printed = capsys.readouterr().out
    assert "drawn by no section" not in printed and "section sweeps" not in printed, printed
    assert any("drawn by no section" in line for line in notes_sync.stale_figures(["propagation"]))
    for only in ("nosuch", "excerpts,nosuch"):
        with pytest.raises(DemoError, match="unknown section.* nosuch; known: colouring"):
            figures.main(check + ["--only", only])
    for only in ("", ","):         # once meant every section, and redrew them all: now named as the mistake
        with pytest.raises(DemoError, match="names no section; name one or more of colouring"):
            figures.main(check + ["--only", only])


def test_excerpts_show_no_solution_markers():
    for path in notes_sync.chapters():
        for match in notes_sync.EXCERPT.finditer(path.read_text()):
            assert "SOLUTION" not in match["body"], f"{path.name}: {match['name']}"


def test_documented_commands_use_the_venv_python():
    """After the quick start only .venv/bin/python has Taichi: a bare `python -m ...` gives an ImportError."""
    for path in notes_sync.documents(NOTES):
        text = notes_sync.INCLUDE.sub("", path.read_text())      # included results record how they were run
        bare = re.findall(r"(?:^|[`\s(])python3? -m (?!venv\b)[\w.]+", text, flags=re.M)
        assert not bare, f"{path.name}: {bare[:3]}"


@pytest.mark.skipif(not Path("/proc/self").exists(), reason="needs /proc, where no folder can be made")
def test_a_figures_folder_that_cannot_be_made_is_a_one_line_error(tmp_path):
    """--out where no folder can be made raised a traceback from mkdir; --check with a folder that does not
    exist blamed a number missing from numbers.json."""
    with pytest.raises(DemoError, match="cannot create the figures folder /proc/vbd-figures: .*; choose another --out"):
        figures.main(["--out", "/proc/vbd-figures", "--only", "excerpts"])
    with pytest.raises(DemoError, match="no figures folder .*missing to check; pass --out with the figures folder"):
        figures.main(["--check", "--out", str(tmp_path / "missing")])
