"""Write frames to an mp4 (imageio-ffmpeg ships its own encoder) or an animated gif."""
import enum

import imageio.v2 as imageio
import imageio.v3 as iio

from .errors import DemoError


class VideoFormat(enum.Enum):
    MP4 = "mp4"
    GIF = "gif"
    NONE = "none"


# A GIF stores each frame's delay in whole hundredths of a second, and browsers play a delay under 2 of them
# as 10: the fastest GIF that plays as written has 2 (50 fps).
GIF_MIN_DELAY = 2


class VideoWriter:
    """Append equally sized RGB frames one at a time; use as a context manager. ``fps`` is the rate the
    video plays at: for a GIF the asked-for rate rounded to a whole number of hundredths of a second a
    frame (30 fps plays at 100 / 3 = 33.3)."""

    def __init__(self, path, video_format, fps, size):
        self.path, self.format, self.fps = path, video_format, fps
        width, height = size
        if video_format is VideoFormat.MP4 and (width % 2 or height % 2):
            raise DemoError(f"mp4 needs an even width and height, got {width}x{height}")
        if video_format is VideoFormat.GIF:
            if fps > 100 / GIF_MIN_DELAY:
                raise DemoError(f"a gif plays at most {100 // GIF_MIN_DELAY} fps (its frame delays are whole "
                                f"hundredths of a second, and browsers slow down delays under "
                                f"{GIF_MIN_DELAY / 100:g} s), got {fps} fps; pass --fps {100 // GIF_MIN_DELAY} "
                                "or less, or --video mp4")
            self.delay = round(100 / fps)        # hundredths of a second a frame
            self.fps = 100 / self.delay
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
            self._writer.write(frame, duration=10 * self.delay, loop=0)
        self.frames += 1

    def __exit__(self, *exc):
        if self._writer is not None:
            self._writer.close()
        return False
