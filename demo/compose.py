"""Lay out a scene's panels in one image and add the text: title, labels, legend."""
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from . import colors
from .render import Body, Renderer, Viewport
from .scenes import Advance, ColorBy

TEXT = (20, 22, 28)
MUTED = (70, 74, 84)
ERROR_TEXT = (180, 40, 30)
LABEL_BACKGROUND = (244, 245, 248)
LINE_SPACING = 1.3      # rows of text are this many font sizes apart


def layout(n_panels, width, height, top):
    """Side-by-side viewports below a title band of ``top`` pixels."""
    edges = np.linspace(0, width, n_panels + 1).round().astype(int)
    return [Viewport(int(a), top, int(b - a), height - top) for a, b in zip(edges[:-1], edges[1:])]


def label_rows(scene):
    """Rows of text the label band of every panel of ``scene`` holds: the most label lines one of its
    panels can have, plus one for a wrapped line or a failure message."""
    rows = 0
    for panel in scene.panels:
        n = 2       # the panel's label and its budget / iteration line
        if panel.newton_ghost:
            n += 3 if scene.advance is Advance.TIME_STEPS else 1     # tip drop, off the ghost, error
        n += bool(panel.probe) + panel.show_inverted + panel.show_drift + (panel.same_wall_time_as is not None)
        rows = max(rows, n)
    return rows + 1


class FrameComposer:
    """Renders a scene's panel states into finished frames (PIL images) of a fixed size."""

    def __init__(self, scene, width, height, arch="cpu"):
        self.scene = scene
        self.width, self.height = width, height
        self.renderer = Renderer(width, height, arch=arch)
        self.font_size = max(9, height // 40)
        self.title_band = int(self.font_size * 1.6 + (self.font_size * 1.3) * len(scene.notes)) + 4
        # at most half of what the title leaves: a tiny image keeps room for the bodies, with fewer rows
        room = max(0, (height - self.title_band) // 2)
        self.rows = max(0, min(label_rows(scene), int((room / self.font_size - 0.5) / LINE_SPACING)))
        # the labels get a band of their own under the title: the bodies are drawn only below it
        self.label_band = int(self.font_size * (0.5 + LINE_SPACING * self.rows))
        self.panels = layout(len(scene.panels), width, height, self.title_band)
        self.viewports = layout(len(scene.panels), width, height, self.title_band + self.label_band)
        self.font = ImageFont.load_default(size=self.font_size)
        self.title_font = ImageFont.load_default(size=int(self.font_size * 1.2))
        self.label_boxes = []       # (x0, y0, x1, y1) pixel box of every label piece of the last frame

    def compose(self, states):
        nearest = self.scene.color_by is ColorBy.COLOR_SETS
        for state, viewport in zip(states, self.viewports):
            body = Body(state.positions, state.faces, state.rgb, state.ghost, nearest_vertex=nearest)
            self.renderer.draw(body, self.scene.camera, viewport, self.scene.grid)
        image = Image.fromarray(self.renderer.image())
        draw = ImageDraw.Draw(image)
        draw.rectangle([0, 0, self.width, self.title_band - 1], fill=(250, 250, 252))
        s = self.font_size
        draw.text((s // 2, s // 4), self.scene.title, font=self.title_font, fill=TEXT)
        for i, note in enumerate(self.scene.notes):
            draw.text((s // 2, int(s * 1.6 + s * 1.3 * i)), note, font=self.font, fill=MUTED)
        self.label_boxes = []
        for state, box in zip(states, self.panels):
            draw.rectangle([box.x, box.y, box.x + box.width - 1, box.y + self.label_band - 1], fill=LABEL_BACKGROUND)
            if box.x > 0:
                draw.line([box.x, box.y, box.x, box.y + box.height], fill=(150, 150, 160), width=1)
            pieces = [(piece, ERROR_TEXT if line.startswith("relative error") else TEXT)
                      for line in state.lines for piece in self.fit(line, box.width - s)]
            if len(pieces) > self.rows:     # never into the bodies' part of the panel
                pieces = pieces[:self.rows]
                if pieces:
                    pieces[-1] = (pieces[-1][0] + " ...", pieces[-1][1])
            for row, (piece, rgb) in enumerate(pieces):
                at = (box.x + s // 2, box.y + s // 4 + int(LINE_SPACING * s * row))
                draw.text(at, piece, font=self.font, fill=rgb)
                self.label_boxes.append(draw.textbbox(at, piece, font=self.font))
        if self.scene.color_by in (ColorBy.DISPLACEMENT, ColorBy.RESIDUAL):
            self._scalar_legend(image, draw)
        return image

    def fit(self, line, width):
        """`line` broken at spaces into pieces at most `width` pixels wide (continuations indented), so
        that a label stays inside its panel."""
        pieces, current = [], ""
        for word in line.split(" "):
            trial = f"{current} {word}" if current.strip() else f"{current}{word}"
            if current.strip() and self.font.getlength(trial) > width:
                pieces.append(current)
                current = "  " + word
            else:
                current = trial
        return pieces + [current]

    def _scalar_legend(self, image, draw):
        """A vertical colour bar in the lower right corner with its range and unit."""
        vp = self.viewports[-1]
        s = self.font_size
        bar_h = vp.height // 3
        x1 = vp.x + vp.width - 3 * s
        x0 = x1 - s
        y1 = vp.y + vp.height - 2 * s
        y0 = y1 - bar_h
        ramp = colors.sequential(np.linspace(1.0, 0.0, max(y1 - y0, 1)))
        bar = np.repeat((ramp * 255).round().astype(np.uint8)[:, None, :], x1 - x0, axis=1)
        image.paste(Image.fromarray(bar), (x0, y0))
        draw.rectangle([x0, y0, x1, y1], outline=TEXT)
        lo, hi = self.scene.color_range
        unit = "m" if self.scene.color_by is ColorBy.DISPLACEMENT else "N"
        name = "moved" if self.scene.color_by is ColorBy.DISPLACEMENT else "residual"
        draw.text((x0 - s * 5, y0 - int(1.4 * s)), f"{name} ({unit}, log)", font=self.font, fill=TEXT)
        draw.text((x0 - int(4.2 * s), y0), f"{hi:.0e}", font=self.font, fill=TEXT)
        draw.text((x0 - int(4.2 * s), y1 - s), f"{lo:.0e}", font=self.font, fill=TEXT)
