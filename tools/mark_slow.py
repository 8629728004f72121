"""Which tests should carry `@pytest.mark.slow`, from the durations of a full run.

A test is slow when its set-up, call and tear-down together take more than --threshold seconds (5 s,
the line the README draws). Measure on an idle machine, the whole suite in one run in one process (`-n 0`:
one test at a time, as the durations mean), then:

    .venv/bin/python -m pytest -q -n 0 --junitxml=run.xml            # preferred: it records skips
    .venv/bin/python tools/mark_slow.py run.xml
or
    .venv/bin/python -m pytest -q -n 0 --durations=0 --durations-min=0 | tee durations.txt
    .venv/bin/python tools/mark_slow.py durations.txt

It prints the tests to mark slow, the tests to unmark, and the test time of the fast subset
(`-m "not slow"`) once both are applied. With --write-durations tests/durations.json --overwrite it also
records the tests that took at least MIN_RECORDED s (and per file the sum of its faster ones), which
tests/conftest.py reads to hand the longest test files out first when the tests run on several workers
(`--dist loadfile`). Which tests carry the marker now is read by collecting `-m slow` with pytest. A
module-scoped fixture's set-up counts for the first test that uses it. Tests the run skipped are not judged
(a junit file says which; durations text does not).
"""
from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MIN_RECORDED = 0.2     # s: `write_durations` sums the faster tests of a file under the file's name
DURATION_LINE = re.compile(r"^\s*(\d+(?:\.\d+)?)s\s+(setup|call|teardown)\s+(\S.*?)\s*$")


class InputError(Exception):
    """A results file this script cannot read; the message names the fix."""


@dataclass(frozen=True)
class Advice:
    """to_mark, to_unmark: (seconds, nodeid) pairs, slowest first; fast_subset_s: seconds of test time
    of the tests left unmarked after the change; unjudged: marked slow but not measured or skipped."""

    to_mark: list
    to_unmark: list
    fast_subset_s: float
    unjudged: list


def durations_from_text(text: str) -> tuple[dict, set]:
    """({nodeid: seconds, summed over set-up, call and tear-down}, set()) from `--durations=0` output."""
    seconds = defaultdict(float)
    for line in text.splitlines():
        match = DURATION_LINE.match(line)
        if match:
            seconds[match.group(3)] += float(match.group(1))
    if not seconds:
        raise InputError("no duration lines (like '12.34s call tests/test_x.py::test_y') found; run pytest "
                         "with --durations=0 --durations-min=0, or pass a --junitxml file")
    return dict(seconds), set()


def durations_from_junit(text: str) -> tuple[dict, set]:
    """({nodeid: seconds}, {skipped nodeids}) from a pytest junit xml file."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as err:
        raise InputError(f"not a readable junit xml file ({err}); pass the file pytest --junitxml wrote") from None
    seconds, skipped = {}, set()
    for case in root.iter("testcase"):
        parts = case.get("classname", "").split(".")          # folders, test module, classes
        module = next((i for i, part in enumerate(parts) if part.startswith("test_")), None)
        if module is None:
            continue
        nodeid = "::".join(["/".join(parts[:module + 1]) + ".py", *parts[module + 1:], case.get("name", "")])
        seconds[nodeid] = float(case.get("time", 0.0))
        if case.find("skipped") is not None:
            skipped.add(nodeid)
    if not seconds:
        raise InputError("the junit file lists no test cases; pass the file of a full pytest run")
    return seconds, skipped


def advise(seconds: dict, skipped: set, marked: set, threshold: float) -> Advice:
    """What to change so that exactly the measured tests over `threshold` seconds carry `slow`."""
    judged = {n: s for n, s in seconds.items() if n not in skipped}
    to_mark = sorted(((s, n) for n, s in judged.items() if s > threshold and n not in marked), reverse=True)
    to_unmark = sorted(((s, n) for n, s in judged.items() if s <= threshold and n in marked), reverse=True)
    slow_after = {n for n, s in judged.items() if s > threshold} | (marked - set(judged))
    fast_subset = sum(s for n, s in seconds.items() if n not in slow_after)
    return Advice(to_mark, to_unmark, fast_subset, sorted(marked - set(judged)))


def write_durations(seconds: dict, skipped: set, path: Path) -> int:
    """Write to `path` (JSON, sorted, 0.1 s steps) {nodeid: seconds} of the run's tests that took at least
    MIN_RECORDED s and were not skipped, and {file: seconds} the sum of each file's faster ones (left out where
    it rounds to 0); returns how many tests it names."""
    measured = {n: s for n, s in seconds.items() if n not in skipped}
    kept = {n: s for n, s in measured.items() if s >= MIN_RECORDED}
    rest = defaultdict(float)
    for n, s in measured.items():
        if s < MIN_RECORDED:
            rest[n.split("::")[0]] += s
    rounded = {n: round(s, 1) for n, s in sorted({**kept, **rest}.items())}
    path.write_text(json.dumps({n: s for n, s in rounded.items() if s > 0}, indent=0) + "\n")
    return len(kept)


def expected_seconds(scopes: dict, seconds: dict) -> dict:
    """{scope: expected seconds} of scopes ({file: [nodeid, ...]}): the file's recorded seconds for its faster
    tests plus those of each of its collected tests that has its own (`write_durations`; a test or file not
    recorded counts 0)."""
    return {f: seconds.get(f, 0.0) + sum(seconds.get(n, 0.0) for n in ids) for f, ids in scopes.items()}


def fitting_groups(groups: dict, expected: dict, workers: int) -> dict:
    """{file: group name} for the groups ({name: [file, ...]}) whose files' expected seconds ({file: s})
    sum to at most one worker's share of the run (all files' seconds over workers): one worker may run
    such a group alone without making the run longer."""
    share = sum(expected.values()) / max(1, workers)
    return {f: name for name, files in groups.items() if sum(expected.get(f, 0.0) for f in files) <= share
            for f in files}


def longest_first(scopes: dict, seconds: dict) -> list:
    """The keys of scopes ({file: [nodeid, ...]}) ordered by their `expected_seconds`, longest first. Ties
    keep their order."""
    expected = expected_seconds(scopes, seconds)
    return sorted(scopes, key=lambda f: -expected[f])


def marked_slow() -> set:
    """Node ids of the tests that carry the slow marker now (pytest --collect-only -m slow)."""
    proc = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-m", "slow",
                           "-p", "no:cacheprovider"], cwd=ROOT, capture_output=True, text=True)
    if proc.returncode not in (0, 5):                     # 5: nothing collected, i.e. no slow test
        raise InputError(f"collecting the slow tests failed ({proc.stdout.strip().splitlines()[-1:]}); "
                         "run pytest --collect-only -m slow to see why")
    return {line.strip() for line in proc.stdout.splitlines() if "::" in line}


def report(advice: Advice, threshold: float) -> str:
    lines = [f"mark slow ({len(advice.to_mark)}: over {threshold:g} s, not marked):"]
    lines += [f"  {s:7.2f} s  {n}" for s, n in advice.to_mark]
    lines += [f"unmark slow ({len(advice.to_unmark)}: marked, {threshold:g} s or less):"]
    lines += [f"  {s:7.2f} s  {n}" for s, n in advice.to_unmark]
    if advice.unjudged:
        lines += [f"left as they are ({len(advice.unjudged)}: marked slow, skipped or not in this run):"]
        lines += [f"             {n}" for n in advice.unjudged]
    lines.append(f"fast subset after the change: {advice.fast_subset_s:.1f} s of test time "
                 "(plus start-up and collection)")
    return "\n".join(lines)


class _Parser(argparse.ArgumentParser):
    """Bad arguments give a one-line error (exit status 2) instead of a usage dump."""

    def error(self, message):
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def positive_seconds(text):
    """An argparse type: a positive, finite number of seconds."""
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return value


def main(argv=None) -> int:
    parser = _Parser(prog="tools/mark_slow.py", description=__doc__.splitlines()[0],
                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("results", type=Path, help="pytest --junitxml file, or saved --durations=0 output")
    parser.add_argument("--threshold", type=positive_seconds, default=5.0, help="seconds above which a test is slow")
    parser.add_argument("--write-durations", type=Path, metavar="JSON", default=None,
                        help="also write the tests' durations there (tests/durations.json: the scheduler's hints)")
    parser.add_argument("--overwrite", action="store_true", help="replace the --write-durations file if it exists")
    args = parser.parse_args(argv)
    try:
        if not args.results.is_file():
            raise InputError(f"{args.results}: no such file; give the junit xml or durations file of a full run")
        if args.write_durations is not None and args.write_durations.exists() and not args.overwrite:
            raise InputError(f"{args.write_durations} exists; pass --overwrite to replace it")
        text = args.results.read_text(errors="replace")
        reader = durations_from_junit if text.lstrip().startswith("<") else durations_from_text
        seconds, skipped = reader(text)
        print(report(advise(seconds, skipped, marked_slow(), args.threshold), args.threshold))
        if args.write_durations is not None:
            kept = write_durations(seconds, skipped, args.write_durations)
            print(f"wrote the durations of {kept} tests to {args.write_durations}")
    except InputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
