"""benchmarks.before_after: both checkouts run the same probe in turn, a commit is checked out into a
worktree that is removed afterwards, and the summary's ratios come from the rounds. No timings are asserted."""
import os
import subprocess

import pytest

from tests.benchmark_checks import benchmark_module, exits_with_one_line, rows

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def worktrees():
    """The folders `git worktree list` names for this repository."""
    listing = subprocess.run(["git", "worktree", "list", "--porcelain"], cwd=ROOT, capture_output=True, text=True)
    return {line.split(" ", 1)[1] for line in listing.stdout.splitlines() if line.startswith("worktree ")}


@pytest.mark.slow
def test_a_checkout_against_itself_takes_the_same_iterates(tmp_path, capsys):
    """--against a folder (this checkout): every probe measurement runs once on each side, and both sides
    reach the same positions to the last digit, since they run the same code."""
    before_after = benchmark_module("before_after")
    assert before_after.main(["--quick", "--no-progress", "--against", ROOT, "--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == \
        f"wrote before_after.csv, before_after.png, summary.md into {tmp_path}"
    data = rows(tmp_path / "before_after.csv")
    names = {r["measurement"] for r in data}
    assert {"VBD iteration, 240 tets (50 per call)", "ns per tet-iteration, 1,920 tets",
            "Newton step, 240 tets", "two-level step, 5 cycles, 240 tets",
            "contact step, 8 cubes on a slab, 600 tets"} <= names
    assert sorted((r["side"], r["measurement"]) for r in data) == sorted(
        (side, name) for side in ("before", "after") for name in names)
    for name in names:
        before, after = ([r for r in data if r["measurement"] == name and r["side"] == side] for side in
                         ("before", "after"))
        assert before[0]["checksum"] == after[0]["checksum"] != "", name
        assert float(before[0]["value"]) > 0 and float(after[0]["value"]) > 0
    summary = (tmp_path / "summary.md").read_text()
    assert "| VBD iteration, 240 tets (50 per call) | ms |" in summary and "Classroom size (after): " in summary
    assert (tmp_path / "before_after.png").stat().st_size > 0


def test_a_commit_is_checked_out_into_a_worktree_removed_afterwards():
    from benchmarks.before_after import Before

    if subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True).returncode != 0:
        pytest.skip("this checkout is not a git repository")
    before = Before("HEAD")
    before.open()
    try:
        assert os.path.isfile(os.path.join(before.folder, "solver", "__init__.py"))
        assert os.path.realpath(before.folder) in {os.path.realpath(w) for w in worktrees()}
    finally:
        before.close()
    assert not os.path.exists(before.folder)
    assert os.path.realpath(before.folder) not in {os.path.realpath(w) for w in worktrees()}


def test_a_folder_that_is_no_checkout_is_refused_in_one_line(tmp_path, capsys):
    exits_with_one_line(capsys, lambda: benchmark_module("before_after").main(
        ["--quick", "--against", str(tmp_path), "--out", str(tmp_path / "out")]), "holds no solver/ package")
    assert not (tmp_path / "out").exists()


def test_the_summary_takes_each_rounds_ratio_and_their_median():
    from benchmarks.before_after import checksum_gap, classroom_line, summarise, verdict

    def row(round_, side, name, value, checksum=""):
        return dict(round=round_, side=side, measurement=name, unit="ms", value=value, checksum=checksum)

    data = [row(1, "before", "VBD iteration, 3,840 tets (50 per call)", 1.0, "10"),
            row(1, "after", "VBD iteration, 3,840 tets (50 per call)", 0.5, "10"),
            row(2, "after", "VBD iteration, 3,840 tets (50 per call)", 0.9, "10"),
            row(2, "before", "VBD iteration, 3,840 tets (50 per call)", 1.0, "10"),
            row(3, "before", "VBD iteration, 3,840 tets (50 per call)", 2.0, "10"),
            row(3, "after", "VBD iteration, 3,840 tets (50 per call)", 1.6, "10"),
            row(1, "before", "ns per tet-iteration, 96,000 tets", 20.0, "4"),
            row(1, "after", "ns per tet-iteration, 96,000 tets", 25.0, "4.000001"),
            row(1, "before", "cold default demo (process)", 7.0),
            row(1, "after", "cold default demo (process)", 7.0),
            row(1, "after", "contact step, 8 cubes on a slab, 600 tets", 5.0, "96")]     # before had no contact
    iteration, large, demo, contact = summarise(data)
    assert (contact["before"], contact["after"], contact["ratio"], contact["rounds"]) == ("", 5.0, "", "")
    assert contact["checksum_gap"] == ""
    assert (iteration["before"], iteration["after"], iteration["rounds"]) == (1.0, 0.9, "0.50, 0.90, 0.80")
    assert iteration["ratio"] == pytest.approx(0.8)
    assert large["checksum_gap"] == pytest.approx(2.5e-7) and demo["checksum_gap"] == ""
    assert checksum_gap(data[:6]) == 0.0
    assert verdict([iteration, demo, contact]) == "Nothing is worse by more than 5%."
    assert verdict([iteration, large]) == "Worse by more than 5%: ns per tet-iteration, 96,000 tets."
    assert iteration["round_ratios"] == pytest.approx([0.5, 0.9, 0.8])
    sizes = dict(classroom=[40, 4, 4], large=[40, 20, 20])
    assert classroom_line([iteration, large], sizes) == ("Classroom size (after): 234.4 ns per tet at 3,840 tets "
                                                         "against 25.0 at 96,000 tets: 9.38x.")
    assert classroom_line([iteration], sizes) == ""
