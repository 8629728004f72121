"""The demo's own error: bad input to the command line or the scenes, reported in one line."""
import solver


class DemoError(solver.VBDError):
    """A user-facing problem with demo arguments, scenes or output files."""
