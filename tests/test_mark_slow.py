"""tools/mark_slow.py: reading a full run's durations and advising which tests carry the slow marker."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from tools import mark_slow

ROOT = Path(__file__).resolve().parent.parent

DURATIONS = """
============================= slowest durations ==============================
6.50s call     tests/test_a.py::test_slow_unmarked
3.00s setup    tests/test_a.py::test_fixture_heavy
2.50s call     tests/test_a.py::test_fixture_heavy
0.80s call     tests/test_b.py::test_fast_marked[x-1]
0.01s teardown tests/test_b.py::test_fast_marked[x-1]
9.00s call     tests/test_b.py::TestGroup::test_slow_marked
0.20s call     tests/test_b.py::test_fast
===== 5 passed in 22.01s =====
"""

JUNIT = """<?xml version="1.0" encoding="utf-8"?><testsuites><testsuite name="pytest">
<testcase classname="tests.test_a" name="test_slow_unmarked" time="6.5"/>
<testcase classname="tests.test_a" name="test_fixture_heavy" time="5.5"/>
<testcase classname="tests.test_b" name="test_fast_marked[x-1]" time="0.81"/>
<testcase classname="tests.test_b.TestGroup" name="test_slow_marked" time="9.0"/>
<testcase classname="tests.test_b" name="test_fast" time="0.2"/>
<testcase classname="tests.test_b" name="test_skipped_on_cpu" time="0.01"><skipped message="no GPU"/></testcase>
</testsuite></testsuites>"""

MARKED = {"tests/test_b.py::test_fast_marked[x-1]", "tests/test_b.py::TestGroup::test_slow_marked",
          "tests/test_b.py::test_skipped_on_cpu", "tests/test_c.py::test_not_in_this_run"}


@pytest.mark.parametrize("reader, text", [(mark_slow.durations_from_text, DURATIONS),
                                          (mark_slow.durations_from_junit, JUNIT)], ids=["durations", "junit"])
def test_advice_marks_tests_over_the_threshold_and_unmarks_the_rest(reader, text):
    seconds, skipped = reader(text)
    assert seconds["tests/test_a.py::test_fixture_heavy"] == pytest.approx(5.5)     # set-up + call
    advice = mark_slow.advise(seconds, skipped, MARKED, threshold=5.0)
    assert [n for _, n in advice.to_mark] == ["tests/test_a.py::test_slow_unmarked",
                                              "tests/test_a.py::test_fixture_heavy"]
    assert [n for _, n in advice.to_unmark] == ["tests/test_b.py::test_fast_marked[x-1]"]
    # a skipped or unmeasured test keeps its marker: this run says nothing about it
    assert advice.unjudged == sorted(MARKED - set(seconds) | skipped)
    assert advice.fast_subset_s == pytest.approx(0.81 + 0.2)           # the skipped test stays slow


@pytest.mark.parametrize("content, match", [
    ("collected 3 items\n3 passed in 1.0s\n", "no duration lines"),
    ("<testsuites><testsuite/></testsuites>", "lists no test cases"),
    ("<testsuites><testcase", "not a readable junit xml file"),
])
def test_unreadable_results_end_in_one_line(tmp_path, capsys, content, match):
    results = tmp_path / "results.txt"
    results.write_text(content)
    assert mark_slow.main([str(results)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and match in err


@pytest.mark.parametrize("threshold", ["nan", "-1", "0", "inf", "five"])
def test_a_threshold_that_is_not_a_positive_number_of_seconds_is_a_one_line_argparse_error(tmp_path, capsys,
                                                                                          threshold):
    results = tmp_path / "durations.txt"
    results.write_text(DURATIONS)
    with pytest.raises(SystemExit) as stop:
        mark_slow.main([str(results), "--threshold", threshold])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--threshold: expected a positive number of seconds, got '{threshold}'" in err


def test_durations_for_the_scheduler_name_the_long_tests_and_sum_the_rest_per_file(tmp_path, capsys,
                                                                                   monkeypatch):
    monkeypatch.setattr(mark_slow, "marked_slow", lambda: MARKED)
    results, out = tmp_path / "run.xml", tmp_path / "durations.json"
    results.write_text(JUNIT.replace('name="test_fast" time="0.2"', 'name="test_fast" time="0.12"')
                       .replace("</testsuite>", '<testcase classname="tests.test_b" name="test_b2" time="0.09"/>'
                                                '<testcase classname="tests.test_c" name="test_c" time="0.01"/>'
                                                "</testsuite>"))
    assert mark_slow.main([str(results), "--write-durations", str(out)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote the durations of 4 tests to {out}"
    written = out.read_text()
    assert mark_slow.main([str(results), "--write-durations", str(out)]) == 1      # never replaced unasked
    err = capsys.readouterr().err
    assert err == f"error: {out} exists; pass --overwrite to replace it\n" and out.read_text() == written
    assert mark_slow.main([str(results), "--write-durations", str(out), "--overwrite"]) == 0
    assert json.loads(out.read_text()) == {"tests/test_a.py::test_slow_unmarked": 6.5,
                                           "tests/test_a.py::test_fixture_heavy": 5.5,
                                           "tests/test_b.py::test_fast_marked[x-1]": 0.8,
                                           "tests/test_b.py::TestGroup::test_slow_marked": 9.0,
                                           "tests/test_b.py": 0.2}   # 0.12 + 0.09; skipped and 0.01 s: left out


def test_the_longest_files_go_first_counting_only_the_collected_tests():
    seconds = {"a.py": 1.0, "a.py::t1": 3.0, "b.py::t1": 2.5, "b.py::t2": 2.5, "c.py": 4.5}
    scopes = {"a.py": ["a.py::t1", "a.py::t2"], "b.py": ["b.py::t1", "b.py::t2"], "c.py": ["c.py::t1"],
              "d.py": ["d.py::t1"], "e.py": ["e.py::t1"]}
    assert mark_slow.longest_first(scopes, seconds) == ["b.py", "c.py", "a.py", "d.py", "e.py"]
    scopes["b.py"] = ["b.py::t1"]                   # -k or -m left one out: 2.5 s
    assert mark_slow.longest_first(scopes, seconds) == ["c.py", "a.py", "b.py", "d.py", "e.py"]


def test_a_group_goes_to_one_worker_only_where_it_fits_in_a_workers_share():
    expected = {"a.py": 30.0, "b.py": 20.0, "c.py": 40.0, "d.py": 10.0}
    groups = {"ab": ["a.py", "b.py"], "cd": ["c.py", "d.py"]}
    assert mark_slow.fitting_groups(groups, expected, 2) == {"a.py": "ab", "b.py": "ab", "c.py": "cd", "d.py": "cd"}
    assert mark_slow.fitting_groups(groups, expected, 3) == {}          # 50 s > 100 s / 3
    assert mark_slow.fitting_groups({"ab": ["a.py", "b.py"], "d": ["d.py"]}, expected, 3) == {"d.py": "d"}


def test_every_file_of_a_scheduling_group_exists():
    """tests/conftest.py keeps the files of a group on one worker (they compile the same kernels): a file
    renamed or removed would silently leave its group."""
    import conftest

    files = [f for group in conftest.SCOPE_GROUPS.values() for f in group]
    assert files and len(files) == len(set(files))
    assert all((Path(__file__).resolve().parent.parent / f).is_file() for f in files), files


def test_the_suite_collects_without_xdist():
    """The scheduler hook in tests/conftest.py is xdist's: without xdist (-p no:xdist) pytest stopped on it as
    an unknown hook before collecting anything."""
    proc = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:xdist",
                           "-p", "no:cacheprovider", "tests/test_mark_slow.py"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "test_the_suite_collects_without_xdist" in proc.stdout
