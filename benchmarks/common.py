"""Shared plumbing of the benchmark scripts: command line, Taichi start-up, CSV, tables, timing."""
import argparse
import contextlib
import csv
import datetime
import math
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")   # Taichi's banner stays off stdout (tables go there)

from demo.cli import HelpFormatter  # noqa: E402  (imports taichi)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
GPU_MEMORY_GB = 16      # CUDA memory Taichi takes at ti.init (its default, 1 GB, is too small for a 1M-tet pile)


def fail(message: str):
    """End a benchmark command with a one-line error (exit status 2), no traceback."""
    print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _shown(value) -> str:
    """A value as it would be typed on the command line: 0.2, 1e+06, 320x180, rest moving."""
    if isinstance(value, (list, tuple)):
        return " ".join(_shown(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


class _HelpFormatter(HelpFormatter):
    """Shows defaults as they would be typed (default: rest moving), not as Python lists."""

    def _get_help_string(self, action):
        help = super()._get_help_string(action)
        return help.replace("%(default)s", _shown(action.default).replace("%", "%%"))


class _Parser(argparse.ArgumentParser):
    """Bad arguments give a one-line error instead of a usage dump.

    ``add_argument(..., quick=VALUE)`` adds an option that takes VALUE under --quick unless it is given,
    and ``add_argument(..., not_quick="why")`` one that cannot be given with --quick; --help says both.
    """

    def __init__(self, *args, quick_text="", **kwargs):
        super().__init__(*args, **kwargs)
        self._quick_text = quick_text
        self._quick = {}        # option -> (action, default, value under --quick or None, why refused or None)
        self._quick_flag = None

    def error(self, message):
        fail(f"{message} (see {self.prog} --help)")

    def add_argument(self, *args, quick=None, not_quick=None, **kwargs):
        if quick is None and not_quick is None:
            action = super().add_argument(*args, **kwargs)
            if action.dest == "quick":
                self._quick_flag = action
                self._describe_quick()
            return action
        default = kwargs.pop("default", False if kwargs.get("action") == "store_true" else None)
        action = super().add_argument(*args, default=None, **kwargs)
        shown = "" if isinstance(default, bool) else f"default: {_shown(default)}; "
        action.help += f" ({shown}--quick: {_shown(quick)})" if quick is not None else \
            f" ({shown}not with --quick: {not_quick})"
        self._quick[action.option_strings[-1]] = (action, default, quick, not_quick)
        self._describe_quick()
        return action

    def _describe_quick(self):
        sets = " ".join(f"{option} {_shown(value)}" for option, (_, _, value, _) in self._quick.items()
                        if value is not None)
        refused = ", ".join(option for option, (_, _, _, why) in self._quick.items() if why is not None)
        what = [part for part in (self._quick_text, sets and f"{sets} unless given",
                                  refused and f"not with {refused}") if part]
        self._quick_flag.help = "a small, fast version (what the tests run)" + (f": {'; '.join(what)}" if what else "")

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        for option, (action, default, quick, why) in self._quick.items():
            value = getattr(namespace, action.dest)
            if value is not None and why is not None and namespace.quick:
                self.error(f"{option} cannot be used with --quick: {why}; drop one of them")
            if value is None:
                value = quick if namespace.quick and quick is not None else default
                setattr(namespace, action.dest, action.type(value) if isinstance(value, str) and action.type else value)
        return namespace, extras


def parser(description: str, default_out: str, quick: str = "") -> argparse.ArgumentParser:
    """An argparse parser with the options every benchmark has: --out, --overwrite, --quick, --no-progress.

    ``quick`` says what --quick changes besides the options added with ``add_argument(..., quick=VALUE)``
    (which keep a value given on the command line); --help lists both. Call ``output_folder(args, files)``
    after parsing: full runs write into ``default_out`` (the committed results), --quick runs into a new
    scratch folder, and existing files are replaced only with --overwrite.
    """
    name = os.path.basename(os.path.normpath(default_out))
    p = _Parser(prog=f"python -m benchmarks.{name}", description=description, formatter_class=_HelpFormatter,
                quick_text=quick)
    p.set_defaults(results_folder=default_out)
    p.add_argument("--out", default=None, help=f"folder for the result files (default: {default_out}; with "
                                                 "--quick a new scratch folder in the system's temporary folder)")
    p.add_argument("--overwrite", action="store_true", help="replace result files already in --out")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return p


def output_folder(args, files) -> str:
    """Create and return the folder the results go to (also stored in ``args.out``), before any work.

    ``files`` are the names the benchmark writes there; if one exists already and --overwrite was not
    given, the command ends with a one-line error instead of replacing it.
    """
    if args.out is None:
        name = os.path.basename(os.path.normpath(args.results_folder))
        args.out = tempfile.mkdtemp(prefix=f"vbd-{name}-quick-") if args.quick else args.results_folder
    if not args.out.strip():
        fail("--out is empty; name a folder, for example --out out/results")
    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as e:
        fail(f"cannot create output folder {args.out}: {e.strerror}; choose another --out")
    if not os.access(args.out, os.W_OK):
        fail(f"cannot write into {args.out}; choose another --out")
    existing = [f for f in files if os.path.exists(os.path.join(args.out, f))]
    if existing and not args.overwrite:
        more = f" and {len(existing) - 1} more" if len(existing) > 1 else ""
        fail(f"{os.path.join(args.out, existing[0])}{more} already exist; pass --overwrite to replace them "
             "or --out to choose another folder")
    return args.out


def print_written(args, files) -> None:
    """Say, as the command's last line, which of `files` it wrote into ``args.out``."""
    written = [f for f in files if os.path.exists(os.path.join(args.out, f))]
    print(f"wrote {', '.join(written)} into {args.out}")


def positive(kind):
    """An argparse type: a number of ``kind`` (int or float) greater than zero."""
    def parse(text):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not value > 0 or not math.isfinite(value):
            what = "whole number" if kind is int else "number"
            raise argparse.ArgumentTypeError(f"expected a positive {what}, got {text!r}")
        return value
    parse.__name__ = f"positive {kind.__name__}"
    return parse


def _float(text):
    """float(text), or None for text that is no number."""
    try:
        return float(text)
    except ValueError:
        return None


def fraction(text):
    """An argparse type: a fraction greater than 0 and at most 1."""
    value = _float(text)
    if value is None or not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction greater than 0 and at most 1, got {text!r}")
    return value


def time_step(text):
    """An argparse type: a time step in seconds within the range a Simulation accepts."""
    from solver.vbd.settings import DT_RANGE

    value = _float(text)
    if value is None or not DT_RANGE[0] <= value <= DT_RANGE[1]:
        raise argparse.ArgumentTypeError(f"expected a time step between {DT_RANGE[0]:g} and {DT_RANGE[1]:g} "
                                         f"seconds, got {text!r}")
    return value


def spectral_radius(text):
    """An argparse type: a Chebyshev rho in (0, 1)."""
    value = _float(text)
    if value is None or not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a Chebyshev rho between 0 and 1 (exclusive), got {text!r}")
    return value


def voxel_resolution(text):
    """An argparse type: voxels along a surface's longest side, within the range the voxeliser accepts."""
    from solver.mesh.voxelize import RESOLUTION_RANGE

    lowest, highest = RESOLUTION_RANGE
    value = _float(text)
    if value is None or not math.isfinite(value) or value != int(value) or not lowest <= value <= highest:
        raise argparse.ArgumentTypeError(f"expected a whole number from {lowest} to {highest}, got {text!r}")
    return int(value)


def init_taichi(threads=None, kernel_profiler=False, arch="cpu"):
    """ti.init on the CPU (or CUDA) in float64, optionally with a thread cap and the kernel profiler.
    A Taichi already running with these settings (a test calling `main()`) is kept, since ti.init frees
    every array made before it."""
    from solver._ti import running_config, ti

    cfg = running_config()
    if (cfg is not None and (cfg.arch == ti.cuda) == (arch == "gpu") and cfg.default_fp == ti.f64
            and cfg.kernel_profiler == kernel_profiler and (not threads or cfg.cpu_max_num_threads == int(threads))):
        return
    kwargs = dict(default_fp=ti.f64, log_level=ti.WARN, kernel_profiler=kernel_profiler)
    if threads:
        kwargs["cpu_max_num_threads"] = int(threads)
    if arch == "gpu":
        kwargs["device_memory_GB"] = GPU_MEMORY_GB
    with contextlib.redirect_stdout(sys.stderr):    # "[Taichi] Starting on arch=...": not a result
        ti.init(arch=ti.cpu if arch == "cpu" else ti.cuda, **kwargs)


def sync():
    """Wait until the running Taichi's kernels are done: a CUDA launch returns before its work is, so a
    timing ends here. On the CPU (or before ``ti.init``) it returns at once."""
    from solver._ti import running_config, ti

    if running_config() is not None:
        ti.sync()


def seconds_per_call(run, min_seconds=0.1, repeats=3):
    """Median wall time of one call of run(1), from `repeats` timings of run(k) lasting
    >= min_seconds / repeats each (k grows by 4x until they do; each waits for the kernels to finish);
    returns (seconds, k * repeats)."""
    run(1)
    k = 1
    while True:
        start = time.perf_counter()
        run(k)
        sync()
        t = time.perf_counter() - start
        if t >= min_seconds / repeats or k >= 1 << 16:
            break
        k *= 4
    samples = [t / k]
    for _ in range(repeats - 1):
        start = time.perf_counter()
        run(k)
        sync()
        samples.append((time.perf_counter() - start) / k)
    return float(np.median(samples)), k * repeats


def write_csv(path: str, rows: list, columns: list = None) -> str:
    """Write a list of dicts as CSV (columns: the union of keys in first-seen order by default)."""
    if columns is None:
        columns = []
        for r in rows:
            for k in r:
                if k not in columns:
                    columns.append(k)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt(r.get(k, "")) for k in columns})
    return path


def read_csv(path: str) -> list:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _fmt(v):
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.6g}"
    return v


def format_seconds(v) -> str:
    """A time for a results table: "12.3 ms", "1.23 s", or "not reached" for inf/NaN."""
    v = float(v)
    if not math.isfinite(v):
        return "not reached"
    return f"{v * 1e3:.3g} ms" if v < 1 else f"{v:.3g} s"


def _cell(v) -> str:
    return f"{float(v):.3g}" if isinstance(v, (float, np.floating)) else str(v)


def nan_as(text: str):
    """A `table` format: `text` ("not reached", "-") for NaN, any other value as `table` shows it."""
    return lambda v: text if isinstance(v, (float, np.floating)) and math.isnan(v) else _cell(v)


def table(rows: list, columns: list, title: str = None, fmt=None) -> str:
    """A markdown table of `rows` (dicts) restricted to `columns`."""
    fmt = fmt or {}

    def cell(r, c):
        v = r.get(c, "")
        if c in fmt and v not in ("", None):
            return fmt[c](v)
        return _cell(v)

    lines = []
    if title:
        lines.append(f"**{title}**\n")
    lines.append("| " + " | ".join(columns) + " |")
    lines.append("|" + "---|" * len(columns))
    for r in rows:
        lines.append("| " + " | ".join(cell(r, c) for c in columns) + " |")
    return "\n".join(lines)


def provenance(argv=None, root=ROOT) -> str:
    """One line saying which command produced a result, when, and on what: the commit of the checkout at
    root, marked "with uncommitted changes" when a tracked file outside benchmarks/results differs from it,
    and whether the optional CHOLMOD was installed (the direct Newton's fastest linear solver:
    `LinearSolver.AUTO` takes it when it is, so Newton timings depend on it)."""
    from solver.newton.direct import DirectSolver, LinearSolver

    argv = sys.argv if argv is None else argv
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True,
                                text=True, timeout=5).stdout.strip()
        edited = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                 ":(exclude)benchmarks/results"], cwd=root, capture_output=True, text=True,
                                timeout=5).stdout.strip()
        if commit and edited:
            commit += " with uncommitted changes"
    except Exception:
        commit = "?"
    cmd = "python -m benchmarks." + os.path.splitext(os.path.basename(argv[0]))[0] + " " + " ".join(argv[1:])
    return (f"`{cmd.strip()}` on {datetime.date.today().isoformat()}, commit {commit or '?'}, "
            f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
            f"{'with' if DirectSolver.installed(LinearSolver.CHOLMOD) else 'without'} CHOLMOD (cvxopt)")


def progress(iterable=None, total=None, desc=None, disable=False):
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, disable=disable, dynamic_ncols=True, file=sys.stderr)


class Timer:
    """Accumulating wall-clock timer: `with timer: ...` adds the elapsed seconds to timer.seconds."""

    def __init__(self):
        self.seconds = 0.0

    def __enter__(self):
        self._t = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds += time.perf_counter() - self._t


def bar_mesh_cells(target_tets: int):
    """Cells (nx, ny, nz) of a 10:1:1 bar with about `target_tets` tets (6 tets per cell)."""
    n = max(1, round((target_tets / 6 / 100) ** (1 / 3)))
    return (10 * n, n, n)


def time_to_reach(times, errors, threshold):
    """First time at which the error is <= threshold, interpolated log-log between checkpoints;
    NaN when never reached."""
    times, errors = np.asarray(times, float), np.asarray(errors, float)
    hit = np.flatnonzero(errors <= threshold)
    if not len(hit):
        return float("nan")
    k = hit[0]
    if k == 0 or times[k - 1] <= 0 or errors[k - 1] <= 0 or errors[k] <= 0:
        return float(times[k])
    le0, le1 = np.log(errors[k - 1]), np.log(errors[k])
    lt0, lt1 = np.log(times[k - 1]), np.log(times[k])
    s = (np.log(threshold) - le0) / (le1 - le0) if le1 != le0 else 1.0
    return float(np.exp(lt0 + s * (lt1 - lt0)))
