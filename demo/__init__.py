"""Scenes, headless rendering, video and the interactive window for the VBD teaching simulator.

Run ``python -m demo --help``. Importing this package has no side effects: Taichi is initialised
only when a simulation or renderer is created.
"""
