"""The speed table of a change: this checkout against an earlier commit, measured in turn in one run.

Each round runs every measurement once in each checkout, each in a new process, with the order of the
two checkouts swapped from round to round; the summary gives the medians and the after/before ratio of
every round. Measured (`benchmarks/speed_probe.py`, in the checkout it times): a VBD iteration of the
stiff stretched bar at classroom size, ns per tet-iteration at ~96k tets, one step of the Newton,
Newton-PCG and two-level methods, a step of 8 cubes with contact (where the checkout has contact);
then the cold default demo (`python -m demo render stiffness_sweep` in a new process) and the interactive
loop (`python -m benchmarks.interactive_fps`) of each checkout.
"Before" is a git worktree of --against, made in a temporary folder and removed at the end (or a folder
holding another checkout); "after" is this checkout as it is, uncommitted changes included.

    python -m benchmarks.before_after --against 2e28f60 --rounds 5 --out benchmarks/results/before_after
    python -m benchmarks.before_after --quick --against HEAD
"""
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks.common import (ROOT, fail, output_folder, parser, positive, print_written, progress, provenance,
                               table, write_csv)

OUTPUTS = ("before_after.csv", "before_after.png", "summary.md")
COLUMNS = ["round", "side", "code", "measurement", "unit", "value", "checksum"]
PARTS = ("vbd", "global", "contact", "demo", "interactive")
FULL_SIZES = dict(classroom=[40, 4, 4], large=[40, 20, 20])     # 3,840 and 96,000 tets
QUICK_SIZES = dict(classroom=[10, 2, 2], large=[20, 4, 4])      # 240 and 1,920 tets
SUMMARY_COLUMNS = ["measurement", "unit", "before", "after", "ratio", "rounds", "checksum_gap"]
SLOWER_BY = 1.05        # what the summary calls worse: after/before above this


def commit_of(ref: str) -> str:
    """The full hash of `ref` in this repository, or None when it names no commit."""
    proc = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}"], cwd=ROOT,
                          capture_output=True, text=True)
    return proc.stdout.strip() if proc.returncode == 0 else None


class Before:
    """The checkout to compare with: a folder given as --against, or a worktree of the commit it names,
    made in a temporary folder by `open()` and removed by `close()`."""

    def __init__(self, against: str):
        self.worktree, self.commit = None, None
        if os.path.isdir(against):
            self.folder = self.label = os.path.abspath(against)
            if not os.path.isfile(os.path.join(self.folder, "solver", "__init__.py")):
                fail(f"--against {against} holds no solver/ package; name a checkout of this project or a commit")
            return
        self.commit = commit_of(against)
        if self.commit is None:
            fail(f"--against {against!r} is neither a folder nor a commit of this repository; "
                 "name one, for example --against HEAD")
        self.folder, self.label = None, self.commit[:7]

    def open(self):
        """Check the commit out into a new temporary worktree (nothing when --against named a folder)."""
        if self.commit is None:
            return
        self.worktree = self.folder = tempfile.mkdtemp(prefix="vbd-before-")
        made = subprocess.run(["git", "worktree", "add", "--detach", self.worktree, self.commit], cwd=ROOT,
                              capture_output=True, text=True)
        if made.returncode != 0:
            shutil.rmtree(self.worktree, ignore_errors=True)
            fail(f"git worktree add failed for {self.label}: {made.stderr.strip().splitlines()[-1]}")

    def close(self):
        """Remove the worktree `open()` made."""
        if self.worktree is not None:
            subprocess.run(["git", "worktree", "remove", "--force", self.worktree], cwd=ROOT, capture_output=True)
            shutil.rmtree(self.worktree, ignore_errors=True)


def run_in(folder: str, argv: list, timeout: float = 1200) -> subprocess.CompletedProcess:
    """Run `python argv` with the checkout at `folder` as working folder and first on the import path."""
    env = dict(os.environ, PYTHONPATH=folder, ENABLE_TAICHI_HEADER_PRINT="0")
    try:
        proc = subprocess.run([sys.executable, *argv], cwd=folder, env=env, capture_output=True, text=True,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        fail(f"{' '.join(argv[:3])} ran over {timeout:g} s in {folder}; measure fewer --parts")
    if proc.returncode != 0:
        fail(f"{' '.join(argv[:3])} failed in {folder}: {(proc.stderr.strip().splitlines() or ['?'])[-1]}")
    return proc


def probe(folder: str, sizes: dict) -> dict:
    """{measurement: (value, unit, checksum)} from `speed_probe.py` run in the checkout at `folder`."""
    proc = run_in(folder, [os.path.join(ROOT, "benchmarks", "speed_probe.py"), json.dumps(sizes)])
    result = json.loads(proc.stdout.strip().splitlines()[-1].removeprefix("RESULT "))
    if not result["solver"].startswith(folder + os.sep):
        fail(f"the probe imported {result['solver']}, not the checkout at {folder}; "
             "uninstall a non-editable copy of the project from this virtual environment")
    return {name: tuple(value) for name, value in result["results"].items()}


def cold_demo(folder: str) -> dict:
    """The wall time of the default demo's render in a new process, with the offline cache as it is."""
    out = tempfile.mkdtemp(prefix="vbd-demo-")
    start = time.perf_counter()
    run_in(folder, ["-m", "demo", "render", "stiffness_sweep", "--out", os.path.join(out, "render")])
    seconds = time.perf_counter() - start
    shutil.rmtree(out, ignore_errors=True)
    return {"cold default demo (process)": (seconds, "s", "")}


def interactive(folder: str, frames: int) -> dict:
    """The interactive loop's median frame, ghosts off and on, from that checkout's own benchmark."""
    out = tempfile.mkdtemp(prefix="vbd-fps-")
    run_in(folder, ["-m", "benchmarks.interactive_fps", "--scenes", "stiffness_sweep", "--frames", str(frames),
                    "--no-progress", "--out", out])
    with open(os.path.join(out, "interactive_fps.csv")) as fh:
        header, *lines = [line.strip().split(",") for line in fh if line.strip()]
    shutil.rmtree(out, ignore_errors=True)
    frame = {row[header.index("ghosts")]: float(row[header.index("median_frame_ms")]) for row in lines}
    return {f"interactive frame, ghost {g}": (frame[g], "ms", "") for g in ("off", "on")}


def measure(folder: str, args) -> dict:
    """Every measurement of the chosen parts, in the checkout at `folder`."""
    results = {}
    if {"vbd", "global", "contact"} & set(args.parts):
        sizes = dict(QUICK_SIZES if args.quick else FULL_SIZES, **{part: part in args.parts
                                                                   for part in ("vbd", "global", "contact")})
        results.update(probe(folder, sizes))
    if "demo" in args.parts:
        results.update(cold_demo(folder))
    if "interactive" in args.parts:
        results.update(interactive(folder, args.frames))
    return results


def checksum_gap(rows: list):
    """The largest relative difference between the two sides' checksums of one measurement ("" without)."""
    sums = {side: [float(r["checksum"]) for r in rows if r["side"] == side and r["checksum"] != ""]
            for side in ("before", "after")}
    if not sums["before"] or not sums["after"]:
        return ""
    return max(abs(a - b) / abs(b) for a in sums["after"] for b in sums["before"])


def summarise(rows: list) -> list:
    """One row per measurement: medians of before and after, the ratio of each round (round_ratios, and as
    text in rounds) and their median."""
    names = list(dict.fromkeys(r["measurement"] for r in rows))
    out = []
    for name in names:
        mine = [r for r in rows if r["measurement"] == name]
        by_round = {}
        for r in mine:
            by_round.setdefault(r["round"], {})[r["side"]] = r["value"]
        ratios = [s["after"] / s["before"] for s in by_round.values() if {"before", "after"} <= set(s)]
        values = {side: [r["value"] for r in mine if r["side"] == side] for side in ("before", "after")}
        out.append(dict(measurement=name, unit=mine[0]["unit"],
                        **{side: float(np.median(v)) if v else "" for side, v in values.items()},
                        ratio=float(np.median(ratios)) if ratios else "",
                        round_ratios=ratios, rounds=", ".join(f"{q:.2f}" for q in ratios),
                        checksum_gap=checksum_gap(mine)))
    return out


def verdict(summary: list) -> str:
    """The line naming the measurements whose after/before median is over SLOWER_BY."""
    worse = [s["measurement"] for s in summary if s["ratio"] != "" and s["ratio"] > SLOWER_BY]
    return (f"Worse by more than {SLOWER_BY - 1:.0%}: {'; '.join(worse)}." if worse else
            f"Nothing is worse by more than {SLOWER_BY - 1:.0%}.")


def classroom_line(summary: list, sizes: dict) -> str:
    """After's ns per tet of the classroom iteration over its ns per tet at the large size, where both ran;
    sizes: the bars' cells (FULL_SIZES or QUICK_SIZES)."""
    small, large = (6 * int(np.prod(sizes[bar])) for bar in ("classroom", "large"))
    after = {s["measurement"]: s["after"] for s in summary}
    iteration_ms = after.get(f"VBD iteration, {small:,} tets (50 per call)")
    large_ns = after.get(f"ns per tet-iteration, {large:,} tets")
    if iteration_ms is None or large_ns is None:
        return ""
    per_tet = 1e6 * iteration_ms / small
    return (f"Classroom size (after): {per_tet:.1f} ns per tet at {small:,} tets against {large_ns:.1f} at "
            f"{large:,} tets: {per_tet / large_ns:.2f}x.")


def plot(summary: list, path: str) -> None:
    """after/before of each measurement both sides took: one dot per round, a bar at the median, lines at 1
    and SLOWER_BY."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = [s for s in summary if s["ratio"] != ""]
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(summary) + 1.2))
    for i, s in enumerate(summary):
        ax.barh(i, s["ratio"], color="#9ab", height=0.6)
        ax.plot(s["round_ratios"], [i] * len(s["round_ratios"]), "k.", ms=5)
    ax.axvline(1.0, color="k", lw=0.8)
    ax.axvline(SLOWER_BY, color="#c33", lw=0.8, ls="--")
    ax.set_yticks(range(len(summary)), [s["measurement"] for s in summary], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("after / before (bar: median; dots: rounds; dashed: 5 % slower)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/before_after",
               quick=f"bars of {6 * np.prod(QUICK_SIZES['classroom']):,} and {6 * np.prod(QUICK_SIZES['large']):,} "
                     f"tets instead of {6 * np.prod(FULL_SIZES['classroom']):,} and "
                     f"{6 * np.prod(FULL_SIZES['large']):,}")
    p.add_argument("--against", default="HEAD", metavar="COMMIT_OR_FOLDER",
                   help="the code before: a commit of this repository (checked out into a temporary worktree) "
                        "or the folder of another checkout")
    p.add_argument("--rounds", type=positive(int), default=5, quick=1, help="rounds of both checkouts in turn")
    p.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS), quick=["vbd", "global", "contact"],
                   help=f"what to measure, of: {', '.join(PARTS)}")
    p.add_argument("--frames", type=positive(int), default=60, quick=5, help="timed frames of the interactive loop")
    args = p.parse_args(argv)
    before = Before(args.against)
    out = output_folder(args, OUTPUTS)
    before.open()
    try:
        sides = {"before": before.folder, "after": ROOT}
        codes = {"before": before.label, "after": "this checkout"}
        if "demo" in args.parts:
            for folder in sides.values():
                cold_demo(folder)           # untimed: fills the offline cache with each side's kernels
        rows = []
        for round_ in progress(range(1, args.rounds + 1), desc="rounds", disable=args.no_progress):
            order = ("before", "after") if round_ % 2 else ("after", "before")
            for side in order:
                for name, (value, unit, total) in measure(sides[side], args).items():
                    rows.append(dict(round=round_, side=side, code=codes[side], measurement=name, unit=unit,
                                     value=value, checksum=total if total == "" else f"{total:.12g}"))
    finally:
        before.close()
    summary = summarise(rows)
    text = table(summary, SUMMARY_COLUMNS,
                 title=f"Before ({codes['before']}) and after (this checkout), medians of {args.rounds} "
                       f"round{'s' if args.rounds > 1 else ''}; "
                       "ratio: after / before, the median of the rounds'",
                 fmt={"before": lambda v: f"{v:.3g}", "after": lambda v: f"{v:.3g}", "ratio": lambda v: f"{v:.2f}",
                      "checksum_gap": lambda v: f"{v:.1g}"})
    lines = [text, "checksum_gap: the largest relative difference between the sums of |x| the two checkouts "
                   "reached (0: the same iterates; the Newton methods stop at a step of 1e-8 of the body's size).",
             verdict(summary), classroom_line(summary, QUICK_SIZES if args.quick else FULL_SIZES)]
    print("\n\n".join(line for line in lines if line))
    write_csv(os.path.join(out, "before_after.csv"), rows, COLUMNS)
    plot(summary, os.path.join(out, "before_after.png"))
    with open(os.path.join(out, "summary.md"), "w") as fh:
        fh.write("\n\n".join([provenance()] + [line for line in lines if line]) + "\n")
    print_written(args, OUTPUTS)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
