"""Write frames to an mp4 (imageio-ffmpeg ships its own encoder) or an animated gif."""
import enum

import imageio.v2 as imageio
import imageio.v3 as iio

from .errors import DemoError


class VideoFormat(enum.Enum):
    MP4 = "mp4"
    GIF = "gif"
    NONE = "none"


class VideoWriter:
    """Append equally sized RGB frames one at a time; use as a context manager."""

    def __init__(self, path, video_format, fps, size):
        self.path, self.format, self.fps = path, video_format, fps
        width, height = size
        if video_format is VideoFormat.MP4 and (width % 2 or height % 2):
            raise DemoError(f"mp4 needs an even width and height, got {width}x{height}")
        self.frames = 0
        self._writer = None

    def __enter__(self):
        if self.format is VideoFormat.MP4:
            # yuv420p plays everywhere; macro_block_size=2 keeps the exact (even) frame size; ffmpeg's
            # warnings (e.g. "not enough frames to estimate rate" for short videos) are not the user's business
            self._writer = imageio.get_writer(self.path, format="FFMPEG", mode="I", fps=self.fps, codec="libx264",
                                              pixelformat="yuv420p", quality=8, macro_block_size=2,
                                              ffmpeg_log_level="error")
        elif self.format is VideoFormat.GIF:
            self._writer = iio.imopen(self.path, "w", plugin="pillow")
        return self

    def append(self, frame):
        if self.format is VideoFormat.MP4:
            self._writer.append_data(frame)
        elif self.format is VideoFormat.GIF:
            self._writer.write(frame, duration=1000.0 / self.fps, loop=0)
        self.frames += 1

    def __exit__(self, *exc):
        if self._writer is not None:
            self._writer.close()
        return False
