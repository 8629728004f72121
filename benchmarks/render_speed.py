"""Headless render speed: one 1280x720 frame of a ~20k-triangle surface on the CPU.

    python -m benchmarks.render_speed --out out/bench
    python -m benchmarks.render_speed --quick        # three small frames, into a scratch folder

Times the Taichi rasteriser (draw + copy of the image to NumPy) over a slowly deforming plate
with a Newton-style ghost and a grid plane, after one warm-up frame (JIT compile). Writes
render_speed.csv to --out and prints the median milliseconds per frame; PNG encoding (Pillow,
compress_level=1) is timed separately because it is not part of rendering.

The renderer keeps the sky gradient + procedural grid of a viewport while the camera stays put
(as in every demo scene); ``--fresh-background`` forgets it before every frame, to time the
worst case of a camera that moves every frame (the column background_recomputed says which).
"""
import argparse
import contextlib
import csv
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import print_written, output_folder, parser, positive, progress

OUTPUTS = ("render_speed.csv", "render_speed_frame.png")


def _triple(text):
    """Box cells "NX,NY,NZ", each a positive whole number."""
    try:
        cells = tuple(int(v) for v in text.split(","))
    except ValueError:
        cells = ()
    if len(cells) != 3 or min(cells) < 1:
        raise argparse.ArgumentTypeError(f"expected three positive whole numbers like 100,48,2, got {text!r}")
    return cells


def _size(text):
    try:
        width, height = (int(v) for v in text.split("x"))
    except ValueError:
        width = height = 0
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT between 16 and 8192, like 1280x720, got {text!r}")
    return width, height


def main(argv=None):
    p = parser(__doc__.split("\n")[0], "benchmarks/results/render_speed")
    p.add_argument("--frames", type=positive(int), default=30, quick=3, help="timed frames")
    p.add_argument("--size", type=_size, default="1280x720", quick="320x180", help="image size WxH")
    p.add_argument("--cells", type=_triple, default="100,48,2", quick="20,10,2",
                   help="box cells; boundary triangles = 4(xy + xz + yz)")
    p.add_argument("--arch", choices=["cpu", "gpu"], default="cpu",
                   help="Taichi backend (gpu: CUDA; without it the CPU, and the summary says so)")
    p.add_argument("--fresh-background", action="store_true",
                   help="recompute the gradient + grid every frame (a moving camera)")
    args = p.parse_args(argv)
    out = Path(output_folder(args, OUTPUTS))
    width, height = args.size
    cells = args.cells

    from PIL import Image

    import solver
    from demo import colors
    from demo.render import Body, Camera, GridPlane, Renderer

    with contextlib.redirect_stdout(sys.stderr):    # "[Taichi] Starting on arch=...": not a result
        solver.ensure_taichi(arch=args.arch)
    arch = "cpu" if solver.backend.running_on_cpu() else "gpu"     # --arch gpu falls back without CUDA
    mesh = solver.box_mesh(size=(1.0, 0.5, 0.02), cells=cells, origin=(-0.5, -0.25, 0.0))
    faces = mesh.boundary_faces()
    rest = mesh.vertices
    renderer = Renderer(width, height, arch=arch)
    camera = Camera(eye=(0.0, -1.3, 0.8), target=(0.0, 0.0, 0.0), fov_degrees=40)
    grid = GridPlane(point=(0.0, 0.0, -0.3))
    t = colors.normalise(rest[:, 0], -0.5, 0.5)
    vertex_rgb = colors.sequential(t)

    rows = []
    for frame in progress(range(args.frames + 1), desc="render_speed", disable=args.no_progress):
        x = rest.copy()
        x[:, 2] += 0.1 * np.sin(3.0 * x[:, 0] + 0.2 * frame)
        body = Body(x, faces, vertex_rgb, ghost_positions=x + (0.0, 0.0, 0.05))
        if args.fresh_background:
            renderer.forget_background()
        start = time.perf_counter()
        renderer.draw(body, camera, grid=grid)
        drawn = time.perf_counter()
        image = renderer.image()
        copied = time.perf_counter()
        if frame == 0:
            Image.fromarray(image).save(out / "render_speed_frame.png")
        else:
            rows.append((frame, 1e3 * (drawn - start), 1e3 * (copied - drawn), 1e3 * (copied - start), _png_ms(image)))

    path = out / "render_speed.csv"
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["frame", "draw_ms", "readback_ms", "render_ms", "png_encode_ms", "background_recomputed"])
        writer.writerows([(r[0], *(f"{v:.3f}" for v in r[1:]), int(args.fresh_background)) for r in rows])
    render_ms = np.median([r[3] for r in rows])
    png_ms = np.median([r[4] for r in rows])
    print(f"{width}x{height}, {len(faces)} triangles (+ ghost), arch={arch}: median {render_ms:.1f} ms per "
          f"frame rendered{' with the background recomputed every frame' if args.fresh_background else ''} "
          f"(PNG encoding adds {png_ms:.1f} ms)")
    print_written(args, OUTPUTS)


def _png_ms(image):
    import io

    from PIL import Image

    start = time.perf_counter()
    Image.fromarray(image).save(io.BytesIO(), format="PNG", compress_level=1)
    return 1e3 * (time.perf_counter() - start)


if __name__ == "__main__":
    main()
