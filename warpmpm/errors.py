"""The package's two error types, so every layer raises the same ones and the CLI maps them to exit codes.

- :class:`InputError`: bad input a user can fix (a missing file, an unknown preset, a slice outside the
  volume, an unstable time step). The CLI prints one ``error:`` line and exits with code 2.
- :class:`SimulationError`: the simulation itself failed (a non-finite value, a particle leaving the
  grid). The CLI prints one ``simulation error:`` line and exits with code 3.
"""

__all__ = ["InputError", "InputWarning", "SimulationError"]


class InputError(ValueError):
    """Bad user input: a missing file, an unknown preset, mismatched grids, an absent organ..."""


class SimulationError(RuntimeError):
    """The simulation produced a non-finite value or a particle tried to leave the grid."""


class InputWarning(UserWarning):
    """Input that is accepted but looks wrong (an implausible organ volume or position: a wrong label preset?)."""
