"""Command line: ``python -m demo [list | render SCENE | interactive SCENE | homework ... | figures ...]``.

With no command it renders the default scene (the stiffness sweep) headless into
``out/stiffness_sweep/``: numbered PNG frames and an mp4.
"""
import os
import re
import sys
import time
from pathlib import Path

if __name__ == "__main__":
    # Taichi prints a version banner to stdout when imported; keep stdout for what the user asked
    # for (help, the scene list, results). ENABLE_TAICHI_HEADER_PRINT=1 brings it back.
    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

import warnings  # noqa: E402

import numpy as np  # noqa: E402

import solver  # noqa: E402

from .cli import (MAX_FPS, MAX_FRAMES, HelpFormatter, Parser, folder, frame_count, frame_rate, image_size,  # noqa: E402
                  iterations, python_command, seconds, start_taichi, time_step, youngs_modulus)
from .errors import DemoError  # noqa: E402

COMMANDS = ("list", "render", "interactive", "homework", "figures")
# the names `render` writes (see planned_files); --overwrite removes earlier ones that this run does not replace
# (earlier_outputs)
FRAME_PATTERN = re.compile(r"frame_\d{4}\.png")
MESH_PATTERN = re.compile(r"frame_\d{4}_panel\d+\.(vtu|ply|obj)")
DELEGATED = {"homework": "demo.homework", "figures": "demo.figures"}


def build_parser():
    from . import scenes
    from .export import ExportFormat
    from .interactive import MIN_SIZE, window_size
    from .video import GIF_MIN_DELAY, VideoFormat

    formatter = HelpFormatter
    parser = Parser(prog=f"{python_command()} -m demo", formatter_class=formatter,
                     description="VBD teaching demos: headless image sequences and video, or an interactive "
                                 "window. With no command: render the stiffness sweep into out/stiffness_sweep/.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.add_parser("list", help="list the scenes", formatter_class=formatter)

    render = sub.add_parser("render", help="render a scene headless to PNG frames (+ video, + meshes)",
                            formatter_class=formatter)
    render.add_argument("scene", nargs="?", default=scenes.DEFAULT_SCENE, help="scene name (see `list`)")
    render.add_argument("--frames", type=frame_count, default=None,
                        help=f"number of frames, at most {MAX_FRAMES} (default: the scene's own)")
    render.add_argument("--out", type=folder, default=None,
                        help="output folder (default: out/SCENE, or out/SCENE_2, _3, ... when it holds an earlier "
                             "render and --overwrite is not given)")
    render.add_argument("--youngs-modulus", type=youngs_modulus, default=None, metavar="PA",
                        help="Young's modulus E of every body in Pa (default: the scene's own)")
    render.add_argument("--iterations", type=iterations, default=None,
                        help="solver iterations per time step of every panel (default: the scene's own)")
    render.add_argument("--dt", type=time_step, default=None, metavar="SECONDS",
                        help="time step h in s (default: the scene's own)")
    render.add_argument("--size", type=image_size, default="1280x720", metavar="WxH", help="image size in pixels")
    render.add_argument("--fps", type=frame_rate, default=None,
                        help=f"video frame rate, at most {MAX_FPS}; a gif's at most {100 // GIF_MIN_DELAY}, rounded "
                             "to a whole number of 1/100 s a frame (default: the scene's own)")
    render.add_argument("--duration", type=seconds, default=None, metavar="SECONDS",
                        help="video length: frames = SECONDS x fps, instead of --frames (default: the scene's own)")
    render.add_argument("--video", choices=[v.value for v in VideoFormat], default="mp4", help="video file to make")
    render.add_argument("--export", choices=[e.value for e in ExportFormat], default="none",
                        help="also write each frame's mesh (vtu: tets; ply/obj: surface)")
    render.add_argument("--overwrite", action="store_true",
                        help="replace the files an earlier render wrote into --out, and remove those of them this "
                             "one does not write (surplus frames and meshes, the video in another format); other "
                             "files are kept")
    render.add_argument("--arch", choices=["cpu", "gpu"], default="cpu", help="Taichi backend")

    interactive = sub.add_parser("interactive", help="open the interactive window (needs Vulkan)",
                                 formatter_class=formatter)
    interactive.add_argument("scene", nargs="?", default=scenes.DEFAULT_SCENE, help="scene name (see `list`)")
    interactive.add_argument("--arch", choices=["cpu", "gpu"], default="cpu", help="Taichi backend")
    interactive.add_argument("--size", type=window_size, default="1280x720", metavar="WxH",
                             help=f"window size in pixels, at least {MIN_SIZE[0]}x{MIN_SIZE[1]}")

    for command, what in (("homework", "homework tools"), ("figures", "lecture figures")):
        if available(command):     # a homework starter has no demo/figures.py: --help does not offer it
            sub.add_parser(command, help=f"{what} (python -m demo {command} --help)", add_help=False)
    return parser


def available(command):
    """Whether the module of a delegated command is in this checkout, beside this file: inside a starter, an
    editable install of the project elsewhere on the import path would offer the project's."""
    return (Path(__file__).parent / f"{DELEGATED[command].rsplit('.', 1)[-1]}.py").is_file()


def list_scenes():
    from . import scenes

    width = max(len(name) for name in scenes.SCENES)
    for scene in scenes.SCENES.values():
        default = " (default)" if scene.name == scenes.DEFAULT_SCENE else ""
        print(f"{scene.name:{width}s} {scene.title}{default}")


def planned_files(out, scene, frames, video, export):
    """Every file a render will write, so existing ones can be refused before any work starts."""
    from .export import ExportFormat
    from .video import VideoFormat

    files = [out / f"frame_{i:04d}.png" for i in range(frames)]
    if video is not VideoFormat.NONE:
        files.append(out / f"{scene.name}.{video.value}")
    if export is not ExportFormat.NONE:
        files += [out / "meshes" / f"frame_{i:04d}_panel{p}.{export.value}"
                  for i in range(frames) for p in range(len(scene.panels))]
    return files


def fresh_folder(out, scene, frames, video, export):
    """``out``, or when it holds files this render would write, the first of out_2, out_3, ... that does
    not: running the default command again keeps the earlier render."""
    candidate, number = out, 1
    while any(f.exists() for f in planned_files(candidate, scene, frames, video, export)):
        number += 1
        candidate = out.with_name(f"{out.name}_{number}")
    return candidate


def earlier_outputs(out, scene, files):
    """The files in ``out`` that an earlier render of ``scene`` wrote and this one, which writes ``files``,
    does not rewrite: surplus frames and meshes, the scene's video in the other format; nothing else."""
    from .video import VideoFormat

    planned = set(files)
    videos = [out / f"{scene.name}.{v.value}" for v in VideoFormat if v is not VideoFormat.NONE]
    named = [f for pattern, where in ((FRAME_PATTERN, out), (MESH_PATTERN, out / "meshes")) if where.is_dir()
             for f in where.iterdir() if pattern.fullmatch(f.name)]
    return [f for f in named + videos if f not in planned and f.is_file()]


def prepare_output(out, scene, files, overwrite):
    try:
        out.mkdir(parents=True, exist_ok=True)
        if any(f.parent != out for f in files):
            (out / "meshes").mkdir(exist_ok=True)
    except OSError as e:
        raise DemoError(f"cannot create output folder {out}: {e.strerror}") from None
    if not out.is_dir():
        raise DemoError(f"output folder {out} is not a folder")
    existing = [f for f in files if f.exists()]
    if existing and not overwrite:
        more = f" and {len(existing) - 1} more" if len(existing) > 1 else ""
        raise DemoError(f"{existing[0]}{more} already exist; pass --overwrite to replace them or --out to "
                        f"choose another folder")
    if overwrite:
        # what an earlier render left that this one does not replace would no longer match the new frames
        try:
            for f in earlier_outputs(out, scene, files):
                f.unlink()
            meshes = out / "meshes"
            if meshes.is_dir() and not any(meshes.iterdir()) and all(f.parent != meshes for f in files):
                meshes.rmdir()      # the earlier render's export folder, emptied: not this render's
        except OSError as e:
            raise DemoError(f"cannot remove the earlier render's {e.filename}: {e.strerror}") from None


def render(args):
    from tqdm import tqdm

    from . import scenes
    from .compose import FrameComposer
    from .export import ExportFormat, export_mesh
    from .runner import SceneRunner, refuse_overrides
    from .video import VideoFormat, VideoWriter

    scene = scenes.get(args.scene)
    fps = args.fps or scene.fps
    if args.frames and args.duration:
        raise DemoError("pass --frames or --duration, not both")
    frames = args.frames or scene.frames
    if args.duration:
        frames = max(1, round(args.duration * fps))
        if frames > MAX_FRAMES:
            raise DemoError(f"--duration {args.duration:g} s at {fps} fps is {frames} frames, more than {MAX_FRAMES}; "
                            "shorten --duration or lower --fps")
    refuse_overrides(scene, youngs_modulus=args.youngs_modulus, iterations=args.iterations, dt=args.dt)
    video_format, export_format = VideoFormat(args.video), ExportFormat(args.export)
    width, height = args.size
    out = args.out if args.out is not None else Path("out") / scene.name
    if args.out is None and not args.overwrite:
        out = fresh_folder(out, scene, frames, video_format, export_format)
    files = planned_files(out, scene, frames, video_format, export_format)
    writer = VideoWriter(files[frames] if video_format is not VideoFormat.NONE else None, video_format, fps,
                         (width, height))
    prepare_output(out, scene, files, args.overwrite)

    started = time.perf_counter()
    start_taichi(args.arch)     # once: the runner and the renderer then use what runs
    runner = SceneRunner(scene, arch=None)
    runner.override(youngs_modulus=args.youngs_modulus, iterations=args.iterations, dt=args.dt)
    composer = FrameComposer(scene, width, height, arch=None)
    try:
        with writer:
            for i in tqdm(range(frames), desc=scene.name, unit="frame", disable=None):
                states = runner.advance()
                image = composer.compose(states)
                image.save(files[i], compress_level=1)
                writer.append(np.asarray(image))
                if export_format is not ExportFormat.NONE:
                    for p, (panel, state) in enumerate(zip(runner.panels, states)):
                        export_mesh(out / "meshes" / f"frame_{i:04d}_panel{p}.{export_format.value}", export_format,
                                    state.positions, panel.tets, panel.faces,
                                    {"step_displacement": state.positions - panel.start})
    except OSError as e:
        raise DemoError(f"cannot write into {out}: {e.strerror or e}") from None
    elapsed = time.perf_counter() - started
    shown = "frame_0000.png" if frames == 1 else f"frame_0000.png ... frame_{frames - 1:04d}.png"
    print(f"wrote {frames} frame{'s' if frames != 1 else ''} to {out}/{shown} in {elapsed:.1f} s")
    if video_format is not VideoFormat.NONE:
        rounded = (f"; {fps} fps asked for: a gif's frame delays are whole hundredths of a second"
                   if writer.fps != fps else "")
        print(f"video: {files[frames]} ({writer.fps:.3g} fps, {width}x{height}{rounded})")
    if export_format is not ExportFormat.NONE:
        print(f"meshes: {out / 'meshes'}/")


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    stderr = sys.stderr

    def one_line_warning(message, category, filename, lineno, file=None, line=None):
        """Warnings as the user sees them: "warning: MESSAGE", no source location."""
        print(f"warning: {message}", file=stderr if file is None else file)

    warnings.showwarning = one_line_warning
    try:
        if argv and argv[0] in DELEGATED:
            return _delegate(argv[0], argv[1:])
        if not argv or (argv[0] not in COMMANDS and argv[0] not in ("-h", "--help")):
            argv = ["render"] + argv
        args = build_parser().parse_args(argv)
        if args.command == "list":
            list_scenes()
        elif args.command == "render":
            render(args)
        elif args.command == "interactive":
            from . import interactive

            interactive.run(args.scene, arch=args.arch, size=args.size)
        return 0
    except solver.VBDError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except NotImplementedError as e:
        from .homework import describe_not_implemented

        print(describe_not_implemented(e), file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def _delegate(command, rest):
    import importlib

    name = DELEGATED[command]
    if not available(command):
        raise DemoError(f"`{command}` is not available: {name} is not in this checkout")
    return importlib.import_module(name).main(rest) or 0


if __name__ == "__main__":
    sys.exit(main())
