"""Lay out a scene's panels in one image and add the text: title, labels, legend."""
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from . import colors
from .render import Body, Renderer, Viewport
from .scenes import ColorBy

TEXT = (20, 22, 28)
MUTED = (70, 74, 84)
ERROR_TEXT = (180, 40, 30)


def layout(n_panels, width, height, top):
    """Side-by-side viewports below a title band of ``top`` pixels."""
    edges = np.linspace(0, width, n_panels + 1).round().astype(int)
    return [Viewport(int(a), top, int(b - a), height - top) for a, b in zip(edges[:-1], edges[1:])]


class FrameComposer:
    """Renders a scene's panel states into finished frames (PIL images) of a fixed size."""

    def __init__(self, scene, width, height, arch="cpu"):
        self.scene = scene
        self.width, self.height = width, height
        self.renderer = Renderer(width, height, arch=arch)
        self.font_size = max(9, height // 40)
        self.title_band = int(self.font_size * 1.6 + (self.font_size * 1.3) * len(scene.notes)) + 4
        self.viewports = layout(len(scene.panels), width, height, self.title_band)
        self.font = ImageFont.load_default(size=self.font_size)
        self.title_font = ImageFont.load_default(size=int(self.font_size * 1.2))

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
        for state, vp in zip(states, self.viewports):
            if vp.x > 0:
                draw.line([vp.x, vp.y, vp.x, vp.y + vp.height], fill=(150, 150, 160), width=1)
            row = 0
            for line in state.lines:
                rgb = ERROR_TEXT if line.startswith("relative error") else TEXT
                for piece in self.fit(line, vp.width - s):
                    draw.text((vp.x + s // 2, vp.y + s // 2 + int(1.3 * s * row)), piece, font=self.font, fill=rgb)
                    row += 1
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
