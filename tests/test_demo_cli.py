"""The command line: outputs, video, overwrite protection, one-line errors."""
import os
import subprocess
import sys
import types
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from demo.__main__ import main

REPO = Path(__file__).resolve().parent.parent


def one_line_error(capsys, argv, match):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "Traceback" not in err, err
    assert match in err, err


@pytest.mark.backend
def test_render_writes_frames_video_and_meshes(tmp_path, capsys):
    out = tmp_path / "sweep"
    argv = ["render", "stiffness_sweep", "--frames", "3", "--size", "64x48", "--out", str(out),
            "--video", "mp4", "--export", "vtu", "--fps", "12"]
    assert main(argv) == 0
    assert f"wrote 3 frames to {out}" in capsys.readouterr().out
    assert sorted(p.name for p in out.glob("frame_*.png")) == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    frames = iio.imread(out / "stiffness_sweep.mp4", index=None)
    assert frames.shape == (3, 48, 64, 3)
    assert len(list((out / "meshes").glob("*.vtu"))) == 6       # 3 frames x 2 panels
    # a second run refuses to overwrite, --overwrite replaces
    one_line_error(capsys, argv, "already exist; pass --overwrite")
    assert main(argv + ["--overwrite"]) == 0


@pytest.mark.backend
def test_gif_and_surface_export(tmp_path):
    out = tmp_path / "g"
    assert main(["render", "twist", "--frames", "2", "--size", "48x32", "--out", str(out), "--video", "gif",
                 "--export", "obj"]) == 0
    assert iio.imread(out / "twist.gif", index=None).shape == (2, 32, 48, 3)
    assert (out / "meshes" / "frame_0001_panel0.obj").stat().st_size > 0


@pytest.mark.backend
def test_gif_frame_delays_match_the_rate_it_reports(tmp_path, capsys):
    """A GIF stores its frame delays in whole hundredths of a second: at --fps 60 it held 10 ms (browsers
    play that at 10 fps) and at the default 30 fps 30 ms (33 fps), while the command said 60 and 30 fps.
    Now the delay is the rate rounded to whole hundredths, and the rate the GIF plays at is the one printed
    (above 50 fps a gif is refused: see test_bad_arguments_give_one_line_errors)."""
    from PIL import Image, ImageSequence

    for fps, delay_ms, shown in [(50, 20, "50 fps"), (30, 30, "33.3 fps"), (24, 40, "25 fps"), (5, 200, "5 fps")]:
        out = tmp_path / str(fps)
        assert main(["render", "twist", "--frames", "3", "--size", "32x32", "--video", "gif", "--fps", str(fps),
                     "--out", str(out)]) == 0
        printed = capsys.readouterr().out
        assert f"twist.gif ({shown}, 32x32" in printed, printed
        assert ("asked for" in printed) == (fps in (30, 24)), printed
        with Image.open(out / "twist.gif") as gif:
            durations = [frame.info["duration"] for frame in ImageSequence.Iterator(gif)]
        assert durations == [delay_ms] * 3, (fps, durations)


def test_existing_user_file_is_never_touched(tmp_path, capsys):
    (tmp_path / "frame_0000.png").write_bytes(b"mine")
    one_line_error(capsys, ["render", "colouring", "--frames", "1", "--out", str(tmp_path)], "--overwrite")
    assert (tmp_path / "frame_0000.png").read_bytes() == b"mine"


@pytest.mark.parametrize("argv, match", [
    (["render", "nope"], "unknown scene 'nope'"),
    (["nope"], "unknown scene 'nope'"),
    (["render", "--size", "12x"], "bad size '12x'"),
    (["render", "--size", "4x4"], "between 16 and 8192"),
    (["render", "--frames", "0"], "expected a positive whole number"),
    (["render", "--video", "avi"], "invalid choice: 'avi'"),
    (["render", "--arch", "tpu"], "invalid choice: 'tpu'"),
    (["render", "--size", "65x48", "--video", "mp4"], "mp4 needs an even width and height"),
    (["interactive", "nope"], "unknown scene 'nope'"),
    (["render", "--youngs-modulus", "-5"], "outside 10 to 1e12 Pa"),
    (["render", "--youngs-modulus", "nan"], "expected Young's modulus in Pa"),
    (["render", "--iterations", "0"], "expected a positive whole number"),
    (["render", "--iterations", "100000"], "more than 10000"),
    (["render", "--dt", "0"], "outside (0, 0.1] s"),
    (["render", "--dt", "1/0"], "outside (0, 0.1] s"),
    (["render", "--dt", "soon"], "expected a time step in s"),
    (["render", "colouring", "--dt", "0.01"], "shows the rest shape"),
    (["render", "probe", "--iterations", "500"], "shows one iteration per frame, so --iterations has nothing"),
    (["render", "sweep_by_colour", "--iterations", "5"], "shows one colour per frame, so --iterations has nothing"),
    (["render", "--fps", "241"], "241 fps is more than 240"),
    (["render", "--fps", "100000"], "100000 fps is more than 240"),
    (["render", "--frames", "10001"], "10001 frames is more than 10000"),
    (["render", "--duration", "3600", "--fps", "240"], "is 864000 frames, more than 10000"),
    (["render", "--video", "gif", "--fps", "51"], "a gif plays at most 50 fps"),
    (["render", "--video", "gif", "--fps", "60"], "pass --fps 50 or less, or --video mp4"),
])
def test_bad_arguments_give_one_line_errors(capsys, tmp_path, argv, match):
    one_line_error(capsys, argv + ["--out", str(tmp_path)] if argv[0] == "render" else argv, match)


def test_unwritable_output_folder(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    one_line_error(capsys, ["render", "colouring", "--frames", "1", "--out", str(blocker / "sub")],
                   "cannot create output folder")


def test_homework_and_figures_are_dispatched_lazily(monkeypatch):
    seen = {}
    for name in ("homework", "figures"):
        module = types.ModuleType(f"demo.{name}")
        module.main = lambda argv, name=name: seen.setdefault(name, argv) and 0
        monkeypatch.setitem(sys.modules, f"demo.{name}", module)
    assert main(["homework", "check", "--x"]) == 0
    assert main(["figures"]) == 0
    assert seen == {"homework": ["check", "--x"], "figures": []}


def test_help_list_and_first_render_in_a_fresh_process_print_no_banner_and_no_precision_warnings(tmp_path):
    """`python -m demo` in fresh processes: help and list answer, and a clean first run (no kernel cache)
    compiles without Taichi precision warnings; stdout carries only what was asked for."""
    env = {**os.environ, "TI_OFFLINE_CACHE": "0"}
    run = lambda *a: subprocess.run([sys.executable, "-m", "demo", *a], cwd=REPO, capture_output=True, text=True,
                                    env=env, timeout=300)
    helped = run("render", "--help")
    assert helped.returncode == 0 and "(default: 1280x720)" in " ".join(helped.stdout.split())
    assert "[Taichi]" not in helped.stdout
    options = " ".join(helped.stdout.split()).split(" --")
    assert all(option.count("(default") <= 1 for option in options), helped.stdout
    assert "(default: None)" not in helped.stdout
    listed = run("list")
    assert listed.returncode == 0 and any(line.startswith("stiffness_sweep ") for line in listed.stdout.splitlines())
    assert "[Taichi]" not in listed.stdout
    rendered = run("render", "colouring", "--size", "64x48", "--video", "none", "--out", str(tmp_path / "c"))
    assert rendered.returncode == 0, rendered.stderr
    assert "precision" not in rendered.stdout + rendered.stderr, rendered.stderr
    assert "[Taichi] version" not in rendered.stdout
    assert "[Taichi]" not in rendered.stdout + rendered.stderr, rendered.stderr


def test_arch_gpu_without_a_gpu_warns_once_in_one_line(tmp_path):
    from solver import _ti as shim

    if shim.is_arch_supported(shim.ti.cuda):
        pytest.skip("a CUDA GPU is here")
    rendered = subprocess.run([sys.executable, "-m", "demo", "render", "twist", "--frames", "1", "--size", "32x32",
                               "--video", "none", "--arch", "gpu", "--out", str(tmp_path / "g")], cwd=REPO,
                              capture_output=True, text=True, timeout=300)
    assert rendered.returncode == 0, rendered.stderr
    assert rendered.stderr == "warning: no CUDA GPU is available here; running on the CPU instead\n"


@pytest.mark.backend
def test_the_default_render_run_twice_keeps_the_first(tmp_path, monkeypatch, capsys):
    """Without --out a second run writes out/SCENE_2 and leaves out/SCENE as it was; with --out it refuses."""
    monkeypatch.chdir(tmp_path)
    argv = ["render", "twist", "--frames", "1", "--size", "32x32", "--video", "none"]
    assert main(argv) == 0
    first = (tmp_path / "out" / "twist" / "frame_0000.png").read_bytes()
    assert main(argv) == 0
    assert "out/twist_2/frame_0000.png" in capsys.readouterr().out
    assert (tmp_path / "out" / "twist" / "frame_0000.png").read_bytes() == first
    assert (tmp_path / "out" / "twist_2" / "frame_0000.png").exists()
    one_line_error(capsys, argv + ["--out", "out/twist"], "--overwrite")


@pytest.mark.backend
def test_overrides_reach_every_panel_and_its_label():
    from demo import scenes
    from demo.runner import SceneRunner

    runner = SceneRunner(scenes.get("resolution_sweep"))
    runner.override(youngs_modulus=2e5, iterations=7, dt=0.01)
    states = runner.advance()
    for p, state in zip(runner.panels, states):
        assert (p.sim.material.youngs_modulus, p.sim.iterations, p.sim.dt, p.sim.frame) == (2e5, 7, 0.01, 1)
        assert state.lines[0] == "changed: E = 2e5 Pa, 7 it., dt = 1/100 s"
        assert state.wave_cells == pytest.approx(p.sim.wave_cells)


def test_hints_name_the_python_that_runs(tmp_path, monkeypatch):
    from demo.cli import python_command

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "executable", str(tmp_path / ".venv" / "bin" / "python"))
    assert python_command() == ".venv/bin/python"
    monkeypatch.setattr(sys, "executable", "/elsewhere/bin/python")
    assert python_command() == "python"


@pytest.mark.backend
def test_overwrite_with_fewer_frames_removes_only_its_own_stale_frames(tmp_path, capsys):
    out = tmp_path / "t"
    argv = ["render", "twist", "--size", "48x32", "--video", "none", "--export", "obj", "--out", str(out)]
    assert main(argv + ["--frames", "3"]) == 0
    mine = [out / "frame_12.png", out / "notes.txt", out / "meshes" / "frame_0002_panel0.obj.bak"]
    for f in mine:
        f.write_text("mine")
    assert main(argv + ["--frames", "1", "--overwrite"]) == 0
    assert sorted(p.name for p in out.glob("frame_*.png")) == ["frame_0000.png", "frame_12.png"]
    assert sorted(p.name for p in (out / "meshes").iterdir()) == ["frame_0000_panel0.obj", "frame_0002_panel0.obj.bak"]
    assert all(f.read_text() == "mine" for f in mine)
    # without --export the earlier meshes go, and so does their folder once empty (a user's file keeps it)
    assert main(argv[:-4] + argv[-2:] + ["--frames", "1", "--overwrite"]) == 0
    assert sorted(p.name for p in (out / "meshes").iterdir()) == ["frame_0002_panel0.obj.bak"]
    (out / "meshes" / "frame_0002_panel0.obj.bak").unlink()
    assert main(argv + ["--frames", "1", "--overwrite"]) == 0
    assert main(argv[:-4] + argv[-2:] + ["--frames", "1", "--overwrite"]) == 0
    assert not (out / "meshes").exists()


def test_overwrite_that_cannot_remove_an_earlier_output_names_it_in_one_line(tmp_path, monkeypatch, capsys):
    """The message names the file or folder that could not go: the emptied meshes/ folder of an earlier
    render too (where no file was removed before it, building the message raised an UnboundLocalError)."""
    import errno

    from demo import __main__ as cli

    out = tmp_path / "t"
    (out / "meshes").mkdir(parents=True)

    def refuse(path):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(Path, "rmdir", refuse)
    with pytest.raises(cli.DemoError, match=r"cannot remove the earlier render's .*meshes: Permission denied$"):
        cli.prepare_output(out, types.SimpleNamespace(name="twist"), [out / "frame_0000.png"], overwrite=True)
    assert (out / "meshes").is_dir()


@pytest.mark.backend
def test_overwrite_removes_the_earlier_video_it_does_not_replace(tmp_path, capsys):
    """--overwrite --video none left the previous run's twist.gif beside the new frames, and --video mp4 an
    earlier gif: a video that no longer matches them. Now --overwrite removes the scene's video in a format
    this run does not write, as it removes surplus frames and meshes; another scene's video and the user's
    files stay."""
    out = tmp_path / "t"
    argv = ["render", "twist", "--frames", "2", "--size", "48x32", "--out", str(out)]
    assert main(argv + ["--video", "gif"]) == 0
    mine = {out / "twist.gif.bak": "mine", out / "stiffness_sweep.mp4": "another scene's", out / "notes.txt": "mine"}
    for path, text in mine.items():
        path.write_text(text)
    assert main(argv + ["--video", "none", "--overwrite"]) == 0
    assert not (out / "twist.gif").exists()
    assert sorted(p.name for p in out.glob("frame_*.png")) == ["frame_0000.png", "frame_0001.png"]
    assert main(argv + ["--video", "gif", "--overwrite"]) == 0
    assert main(argv + ["--video", "mp4", "--overwrite"]) == 0
    assert (out / "twist.mp4").exists() and not (out / "twist.gif").exists()
    assert all(path.read_text() == text for path, text in mine.items())
    capsys.readouterr()


def test_empty_out_is_refused(capsys):
    one_line_error(capsys, ["render", "colouring", "--out", ""], "empty --out would write into the current folder")


@pytest.mark.parametrize("argv, match", [
    (["figures", "--size", "10"], "bad size '10'"),
    (["figures", "--only", "excerpts", "--notes", "/nonexistent"], "no lecture-note chapters"),
    (["figures", "--check", "--notes", "/nonexistent"], "no lecture-note chapters"),
])
def test_figures_bad_arguments_give_one_line_errors(capsys, argv, match):
    one_line_error(capsys, argv, match)


@pytest.mark.parametrize("mode", [["--only", "excerpts"], ["--check"]])
@pytest.mark.parametrize("under", ["", "figures"])
def test_figures_out_must_be_a_folder(tmp_path, capsys, mode, under):
    """An existing file as --out (or above it) is a one-line error: it was a FileExistsError traceback, or
    with --check a misleading 'no manifest.json'. The file is untouched."""
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    one_line_error(capsys, ["figures", *mode, "--out", str(notes / under)],
                   "--out must be a folder, but notes.txt is a file")
    assert notes.read_text() == "mine"


def test_ply_export_writes_32_bit_faces_without_warnings(tmp_path, capfd):
    import meshio
    import solver
    from demo.export import ExportFormat, export_mesh

    mesh = solver.box_mesh(size=(1.0, 0.2, 0.2), cells=(3, 1, 1))
    faces = mesh.boundary_faces()
    export_mesh(tmp_path / "m.ply", ExportFormat.PLY, mesh.vertices, mesh.tets, faces)
    captured = capfd.readouterr()
    assert "64-bit" not in captured.out + captured.err
    back = meshio.read(tmp_path / "m.ply")
    used = np.unique(faces)
    np.testing.assert_allclose(back.points, mesh.vertices[used])
    np.testing.assert_array_equal(used[back.cells[0].data], faces)


@pytest.mark.backend
def test_duration_sets_the_number_of_frames(tmp_path, capsys):
    out = tmp_path / "c"
    assert main(["render", "colouring", "--duration", "1.5", "--fps", "2", "--size", "64x48", "--out", str(out),
                 "--video", "none"]) == 0
    assert f"wrote 3 frames to {out}" in capsys.readouterr().out
    assert len(list(out.glob("frame_*.png"))) == 3
    one_line_error(capsys, ["render", "colouring", "--duration", "2", "--frames", "3", "--out", str(out)],
                   "--frames or --duration, not both")
    one_line_error(capsys, ["render", "colouring", "--duration", "-1"], "duration in seconds")


@pytest.mark.backend
def test_one_frame_is_singular(tmp_path, capsys):
    out = tmp_path / "one"
    assert main(["render", "colouring", "--size", "64x48", "--out", str(out), "--video", "none"]) == 0
    text = capsys.readouterr().out
    assert f"wrote 1 frame to {out}/frame_0000.png in " in text and "frames" not in text


def test_the_readme_names_every_scene_demo_list_shows():
    """The README's scene list had left out three of the scenes `demo list` prints."""
    from demo.scenes import SCENES

    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    listed = readme.split("Scenes (`demo list`):", 1)[1].split("\n\n", 1)[0]
    assert [name for name in SCENES if f"`{name}`" not in listed] == []
