"""Reproducible benchmarks of the VBD solver: run time against error, throughput, numerical stress,
and what a scene skips. Each script writes CSV and PNG files into --out and prints a summary table;
run them as modules from the repository root, e.g. ``python -m benchmarks.pareto --quick``."""
