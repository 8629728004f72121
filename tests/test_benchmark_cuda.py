"""benchmarks/cuda.py on this run's backend: its GPU columns measured on the CPU in the default run (the same
code), its refusal without a GPU, and its results kept when a run is stopped part way. A file of its own:
it compiles the contact kernels, and runs on the worker of the contact tests (tests/conftest.py)."""
import pytest

from tests.benchmark_checks import benchmark_module, exits_with_one_line, rows


@pytest.mark.backend
def test_cuda_quick_runs_the_gpu_columns_on_the_runs_backend(tmp_path, capsys, arch):
    """benchmarks.cuda's scenes on this run's backend (the CPU in the default run: the same code), every
    measurement written and sane; the pile falls into its box and never crosses."""
    assert benchmark_module("cuda").main(["--quick", "--arch", arch, "--no-progress", "--min-seconds", "0.001",
                                          "--out", str(tmp_path)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == f"wrote cuda.csv, summary.md into {tmp_path}"
    data = rows(tmp_path / "cuda.csv")
    assert {r["arch"] for r in data} == {arch}
    sweeps = [r for r in data if r["measurement"] == "sweep"]
    assert [(r["precision"], int(r["tets"])) for r in sweeps] == [("float64", 144), ("float64", 1152),
                                                                  ("float32", 144), ("float32", 1152)]
    assert all(float(r["ns_per_tet_iter"]) > 0 and float(r["first_iteration_s"]) > 0 for r in sweeps)
    (apart,) = [r for r in data if r["measurement"].startswith("apart")]
    assert int(apart["contacts"]) == 0 and float(apart["contact_per_none"]) > 0
    (touching,) = [r for r in data if r["measurement"].startswith("touching")]
    assert int(touching["contacts"]) > 0 and float(touching["detect_per_sweep"]) > 0
    (pile,) = [r for r in data if r["measurement"] == "falling pile"]
    assert int(pile["bodies"]) == 8 and int(pile["contacts"]) > 0, "the bottom layer rests on the box"
    assert 0 < float(pile["min_separation_mm"]) < 5, "closer than the 5 mm radius, never touching"
    assert float(pile["step_ms"]) > 0 and float(pile["detections_per_step"]) >= 0
    summary = (tmp_path / "summary.md").read_text()
    assert "| falling pile |" in summary and "so far" not in summary


def test_cuda_without_a_gpu_says_so_in_one_line(capsys, cuda_present, tmp_path):
    if cuda_present:
        pytest.skip("this machine has a CUDA GPU")
    def without_arch():
        benchmark_module("cuda").main(["--quick", "--out", str(tmp_path / "out")])

    exits_with_one_line(capsys, without_arch,
                        "no CUDA GPU on this machine; run it where there is one, or pass --arch cpu")
    assert not (tmp_path / "out").exists(), "nothing is made before the refusal"


@pytest.mark.backend
def test_cuda_writes_its_results_after_every_measurement(tmp_path, capsys, arch, monkeypatch):
    """A run stopped part way (a GPU lent for minutes, taken back) leaves the rows measured so far, and its
    summary says how far it got."""
    cuda = benchmark_module("cuda")

    def stop(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cuda, "measure_apart", stop)
    exits_with_one_line(capsys, lambda: cuda.main(["--quick", "--arch", arch, "--no-progress", "--parts", "sweep",
                                                    "contact", "--out", str(tmp_path)]),
                         "interrupted: ")
    assert [(r["precision"], r["tets"]) for r in rows(tmp_path / "cuda.csv")] == [
        ("float64", "144"), ("float64", "1152"), ("float32", "144"), ("float32", "1152")]
    assert "(so far: 4 of 5 measurements)" in (tmp_path / "summary.md").read_text().splitlines()[0]
