"""The project's own exception types.

Every problem a user can cause (a bad mesh file, a nonsense parameter) raises one of these with a
one-line message that names the problem and the fix, so a CLI can print ``str(err)`` and exit.
"""


class VBDError(Exception):
    """Base class of every error this project raises on purpose."""


class MeshError(VBDError, ValueError):
    """A mesh that cannot be simulated: missing/unreadable file, no tets, bad indices or geometry."""


class ConfigError(VBDError, ValueError):
    """A parameter outside its meaningful range (negative time step, Poisson ratio >= 0.5, ...)."""


def enum_value(cls, value, what: str):
    """`value` as a member of the Enum `cls`, given the member or its value (name); else a ConfigError
    naming `what` and the accepted values."""
    if isinstance(value, cls):
        return value
    try:
        return cls(getattr(value, "value", value))
    except ValueError:
        names = ", ".join(repr(m.value) for m in cls)
        raise ConfigError(f"unknown {what} {value!r}; use one of {names}") from None


class MeshWarning(UserWarning):
    """A mesh was loaded, but something about it was changed or may cause trouble (one-line message)."""


class MeshQualityWarning(MeshWarning):
    """The mesh has badly shaped tets (slivers) that an unconverged solver can invert."""
