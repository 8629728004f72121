"""What tests/test_benchmarks.py and tests/test_benchmark_cuda.py share: reading a benchmark's CSV, its
module, and the check that a refusal is one line."""
import csv
import importlib

import pytest


def rows(path):
    """The rows of a CSV file as dicts of strings."""
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def benchmark_module(name):
    """The benchmark module benchmarks.<name>."""
    return importlib.import_module(f"benchmarks.{name}")


def exits_with_one_line(capsys, run, match):
    """run() exits with status 2 and one line on stderr, "error: ...", containing match."""
    with pytest.raises(SystemExit) as e:
        run()
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and match in err, err
