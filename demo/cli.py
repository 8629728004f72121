"""Argument parsing shared by the demo's commands: one-line errors, defaults in --help, value types."""
import argparse
import re
from pathlib import Path

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


def seconds(text):
    """A duration in seconds, more than 0 and at most an hour."""
    try:
        value = float(text)
    except ValueError:
        value = 0.0
    if not (0.0 < value <= 3600.0):
        raise argparse.ArgumentTypeError(f"expected a duration in seconds between 0 and 3600, got {text!r}")
    return value
