"""Argument parsing shared by the demo's commands: one-line errors, defaults in --help, value types."""
import argparse
import contextlib
import io
import math
import re
import sys
import warnings
from pathlib import Path

import solver

from .errors import DemoError


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Adds "(default: ...)" to an option's help unless the help already says its default."""

    def _get_help_string(self, action):
        if "default" in (action.help or "") or action.default in (None, "") or isinstance(action.default, bool):
            return action.help
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one-line DemoErrors instead of usage dumps."""

    def error(self, message):
        raise DemoError(f"{message} (see {self.prog} --help)")


def image_size(text):
    """WIDTHxHEIGHT in pixels, each between 16 and 8192."""
    match = re.fullmatch(r"(\d+)x(\d+)", text)
    if not match:
        raise argparse.ArgumentTypeError(f"bad size {text!r}: expected WIDTHxHEIGHT, for example 1280x720")
    width, height = int(match[1]), int(match[2])
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise argparse.ArgumentTypeError(f"bad size {text!r}: width and height must be between 16 and 8192")
    return width, height


def folder(text):
    """An output folder; an empty name (which would mean the current folder) is refused."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty --out would write into the current folder; name a folder, "
                                         "for example --out out/mine")
    return Path(text)


def positive(text):
    """A whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {text!r}")
    return value


MAX_FPS = 240
MAX_FRAMES = 10000      # the frames are numbered frame_0000.png ... frame_9999.png


def frame_rate(text):
    """Frames per second, a whole number from 1 to MAX_FPS."""
    value = positive(text)
    if value > MAX_FPS:
        raise argparse.ArgumentTypeError(f"{value} fps is more than {MAX_FPS}; pick a lower rate")
    return value


def frame_count(text):
    """A number of frames, 1 to MAX_FRAMES."""
    value = positive(text)
    if value > MAX_FRAMES:
        raise argparse.ArgumentTypeError(f"{value} frames is more than {MAX_FRAMES} (frame_0000.png to "
                                         f"frame_{MAX_FRAMES - 1:04d}.png); render fewer")
    return value


def seconds(text):
    """A duration in seconds, more than 0 and at most an hour."""
    try:
        value = float(text)
    except ValueError:
        value = 0.0
    if not (0.0 < value <= 3600.0):
        raise argparse.ArgumentTypeError(f"expected a duration in seconds between 0 and 3600, got {text!r}")
    return value


def python_command():
    """How the user runs this Python, for hints: the interpreter's path relative to the current folder
    (".venv/bin/python") when it lies inside it, else "python" (an activated virtual environment or
    the system's)."""
    try:
        return str(Path(sys.executable).relative_to(Path.cwd()))
    except ValueError:
        return "python"


def _number(text, what):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def youngs_modulus(text):
    """Young's modulus E in Pa, from 10 Pa to 1e12 Pa."""
    value = _number(text, "Young's modulus in Pa, for example 1e6")
    if not 10.0 <= value <= 1e12:
        raise argparse.ArgumentTypeError(f"Young's modulus {text!r} Pa is outside 10 to 1e12 Pa; rubber is about "
                                         "1e6, steel 2e11")
    return value


def iterations(text):
    """Iterations per time step, 1 to 10000."""
    value = positive(text)
    if value > 10000:
        raise argparse.ArgumentTypeError(f"{value} iterations per step is more than 10000; pick fewer")
    return value


def time_step(text):
    """A time step in s, above 0 and at most 0.1, as a number or a fraction ("1/120")."""
    what = "a time step in s, for example 0.01 or 1/120"
    numerator, _, denominator = text.partition("/")
    value = _number(numerator, what) / (_number(denominator, what) if denominator else 1.0) if denominator != "0" \
        else 0.0
    if not 0.0 < value <= 0.1:
        raise argparse.ArgumentTypeError(f"time step {text!r} s is outside (0, 0.1] s; the scenes use 1/60 = 0.0167")
    return value


def start_taichi(arch):
    """Start Taichi on ``arch`` without its "[Taichi] Starting on arch=..." line (warnings still show)."""
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stderr(io.StringIO()):
        solver.ensure_taichi(arch)
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
