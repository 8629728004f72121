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
# the frame size the scenes' cameras are chosen for: a panel narrower than there is fitted by its width
DEFAULT_SIZE = (1280, 720)
REMEMBERED_TEXTS = 4096     # pieces of text whose layout a composer keeps before it starts again


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


class FrameLayout:
    """Where the parts of a scene's frame of ``width`` x ``height`` pixels go: the title band on top (the
    title and the notes, wrapped to the width, at most half the height), each panel's label band below
    it and the panel's viewport for the bodies below that."""

    def __init__(self, scene, width, height):
        self.scene = scene
        self.width, self.height = width, height
        self.font_size = max(9, height // 40)
        self.font = ImageFont.load_default(size=self.font_size)
        self.title_font = ImageFont.load_default(size=int(self.font_size * 1.2))
        self._pieces = {}           # (line, width, font) -> `fit`'s pieces: most labels repeat from frame to frame
        self.title_rows, self.title_band = self._title_rows()
        # at most half of what the title leaves: a tiny image keeps room for the bodies, with fewer rows
        room = max(0, (height - self.title_band) // 2)
        self.rows = max(0, min(label_rows(scene), int((room / self.font_size - 0.5) / LINE_SPACING)))
        # the labels get a band of their own under the title: the bodies are drawn only below it
        self.label_band = int(self.font_size * (0.5 + LINE_SPACING * self.rows))
        self.panels = layout(len(scene.panels), width, height, self.title_band)
        self.viewports = layout(len(scene.panels), width, height, self.title_band + self.label_band)

    def _title_rows(self):
        """([(text, font, colour, (x, y))] of the title band, its height): the title's and then the notes'
        pieces, as many as fit in half the height, the last one then ending in " ..."."""
        s = self.font_size
        width = self.width - s
        pieces = ([(piece, self.title_font, TEXT) for piece in self.fit(self.scene.title, width, self.title_font)]
                  + [(piece, self.font, MUTED) for note in self.scene.notes for piece in self.fit(note, width)])
        n_title = sum(font is self.title_font for _, font, _ in pieces)
        title_pitch = self.title_font.size * LINE_SPACING

        def at(row):        # the top of row `row`; at(number of rows) is where the band's text ends
            if row < n_title:
                return s // 4 + int(title_pitch * row)
            return int(s * 1.6 + title_pitch * (n_title - 1) + s * 1.3 * (row - n_title))

        kept = len(pieces)
        while kept and at(kept) + 4 > self.height // 2:
            kept -= 1
        rows = [(text, font, rgb, (s // 2, at(row))) for row, (text, font, rgb) in enumerate(pieces[:kept])]
        if rows and kept < len(pieces):
            text, font, rgb, xy = rows[-1]
            rows[-1] = (self.shortened(text, width, font), font, rgb, xy)
        return rows, (at(kept) + 4 if kept else 0)

    def fit(self, line, width, font=None):
        """`line` broken at spaces into pieces at most `width` pixels wide in `font` (default: the label
        font), continuations indented, so that a label stays inside its panel; a word wider than that is
        broken where it reaches the width, and a line gets no pieces where not one letter fits."""
        font = font or self.font
        known = self._pieces.get((line, width, font))
        if known is None:
            if len(self._pieces) >= REMEMBERED_TEXTS:      # labels with numbers that change every frame
                self._pieces.clear()
            known = self._pieces[line, width, font] = self._fit(line, width, font)
        return list(known)

    @staticmethod
    def _fit(line, width, font):
        """`fit`'s pieces, worked out."""
        pieces, current = [], ""
        for word in line.split(" "):
            trial = f"{current} {word}" if current.strip() else f"{current}{word}"
            if current.strip() and font.getlength(trial) > width:
                pieces.append(current)
                current = "  " + word
            else:
                current = trial
        pieces.append(current)
        broken = []
        for piece in pieces:
            while font.getlength(piece) > width:
                n = max((k for k in range(len(piece) + 1) if font.getlength(piece[:k]) <= width), default=0)
                if not piece[:n].strip():
                    return []
                broken.append(piece[:n])
                piece = "  " + piece[n:]
            broken.append(piece)
        return broken

    @staticmethod
    def shortened(text, width, font):
        """`text` cut short to end in " ..." within `width` pixels ("" where not even a letter fits)."""
        while text.strip() and font.getlength(text + " ...") > width:
            text = text[:-1].rstrip()
        return text + " ..." if text.strip() else ""


class FrameComposer(FrameLayout):
    """Renders a scene's panel states into finished frames (PIL images) of a fixed size."""

    def __init__(self, scene, width, height, arch="cpu"):
        super().__init__(scene, width, height)
        self.renderer = Renderer(width, height, arch=arch)
        # a panel narrower than at the default size shows what it showed there: the cameras are chosen for it
        self.framed = [(vp.width, vp.height) for vp in FrameLayout(scene, *DEFAULT_SIZE).viewports]
        self.label_boxes = []       # (x0, y0, x1, y1) pixel box of every label piece of the last frame
        self.text_boxes = []        # the same of every piece of text of the last frame: title, notes, labels, legend
        self._title = None          # (the title band as drawn, its text boxes): the same in every frame
        self._extents = {}          # (text, font) -> its box relative to where it is drawn

    def compose(self, states):
        nearest = self.scene.color_by is ColorBy.COLOR_SETS
        for state, viewport, framed in zip(states, self.viewports, self.framed):
            body = Body(state.positions, state.faces, state.rgb, state.ghost, nearest_vertex=nearest)
            self.renderer.draw(body, self.scene.camera, viewport, self.scene.grid, framed)
        image = Image.fromarray(self.renderer.image())
        draw = ImageDraw.Draw(image)
        self._draw_title(image, draw)
        s = self.font_size
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
                    pieces[-1] = (self.shortened(pieces[-1][0], box.width - s, self.font), pieces[-1][1])
            for row, (piece, rgb) in enumerate(pieces):
                at = (box.x + s // 2, box.y + s // 4 + int(LINE_SPACING * s * row))
                self.label_boxes.append(self._text(draw, at, piece, self.font, rgb))
        if self.scene.color_by in (ColorBy.DISPLACEMENT, ColorBy.RESIDUAL):
            self._scalar_legend(image, draw)
        return image

    def _draw_title(self, image, draw):
        """The title band: the title and the notes, drawn once and pasted into every later frame."""
        if self._title is not None:
            band, boxes = self._title
            if band is not None:
                image.paste(band, (0, 0))
            self.text_boxes = list(boxes)
            return
        self.text_boxes = []
        if self.title_band:
            draw.rectangle([0, 0, self.width, self.title_band - 1], fill=(250, 250, 252))
        for text, font, rgb, at in self.title_rows:
            self._text(draw, at, text, font, rgb)
        band = image.crop((0, 0, self.width, self.title_band)) if self.title_band else None
        self._title = band, list(self.text_boxes)

    def _text(self, draw, at, text, font, rgb):
        """Draw `text` with its top left at `at`; returns (and records) its pixel box."""
        draw.text(at, text, font=font, fill=rgb)
        extent = self._extents.get((text, font))
        if extent is None:
            if len(self._extents) >= REMEMBERED_TEXTS:
                self._extents.clear()
            extent = self._extents[text, font] = draw.textbbox((0, 0), text, font=font)
        box = (at[0] + extent[0], at[1] + extent[1], at[0] + extent[2], at[1] + extent[3])
        self.text_boxes.append(box)
        return box

    def _scalar_legend(self, image, draw):
        """A vertical colour bar in the lower right corner with its range and unit, where it fits into the
        last panel's viewport."""
        vp = self.viewports[-1]
        s = self.font_size
        bar_h = vp.height // 3
        x1 = vp.x + vp.width - 3 * s
        x0 = x1 - s
        y1 = vp.y + vp.height - 2 * s
        y0 = y1 - bar_h
        lo, hi = self.scene.color_range
        unit = "m" if self.scene.color_by is ColorBy.DISPLACEMENT else "N"
        name = "moved" if self.scene.color_by is ColorBy.DISPLACEMENT else "residual"
        texts = [((x0 - s * 5, y0 - int(1.4 * s)), f"{name} ({unit}, log)"), ((x0 - int(4.2 * s), y0), f"{hi:.0e}"),
                 ((x0 - int(4.2 * s), y1 - s), f"{lo:.0e}")]
        boxes = [draw.textbbox(at, text, font=self.font) for at, text in texts]
        if y0 >= y1 or not all(vp.x <= b[0] and vp.y <= b[1] and b[2] <= vp.x + vp.width and b[3] <= vp.y + vp.height
                               for b in boxes):
            return
        ramp = colors.sequential(np.linspace(1.0, 0.0, y1 - y0))
        bar = np.repeat((ramp * 255).round().astype(np.uint8)[:, None, :], x1 - x0, axis=1)
        image.paste(Image.fromarray(bar), (x0, y0))
        draw.rectangle([x0, y0, x1, y1], outline=TEXT)
        for at, text in texts:
            self._text(draw, at, text, self.font, TEXT)
