"""The package's two error types, so every layer raises the same ones and the CLI maps them to exit codes.

- :class:`InputError`: bad input a user can fix (a missing file, an unknown preset, a slice outside the
  volume, an unstable time step). The CLI prints one ``error:`` line and exits with code 2.
- :class:`SimulationError`: the simulation itself failed (a non-finite value, a particle leaving the
  grid). The CLI prints one ``simulation error:`` line and exits with code 3.
"""

__all__ = ["InputError", "InputWarning", "SimulationError", "check_input_file"]


class InputError(ValueError):
    """Bad user input: a missing file, an unknown preset, mismatched grids, an absent organ..."""


class SimulationError(RuntimeError):
    """The simulation produced a non-finite value or a particle tried to leave the grid."""


class InputWarning(UserWarning):
    """Input that is accepted but looks wrong (an implausible organ volume or position: a wrong label preset?)."""


def check_input_file(path, what: str, fix: str = "") -> None:
    """Refuse an input file that is missing, not a regular file (a folder, a device, a pipe) or empty, saying which."""
    import os

    hint = f"; {fix}" if fix else ""
    if not os.path.exists(path):
        raise InputError(f"{what} not found: {path}{hint}")
    if not os.path.isfile(path):
        kind = "a folder" if os.path.isdir(path) else "not a regular file (a device or a pipe?)"
        raise InputError(f"{what} {path} is {kind}; give the file itself{hint}")
    if os.path.getsize(path) == 0:
        raise InputError(f"{what} {path} is empty (0 bytes){hint}")
