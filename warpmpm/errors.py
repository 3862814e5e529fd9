"""The package's two error types, so every layer raises the same ones and the CLI maps them to exit codes.

- :class:`InputError`: bad input a user can fix (a missing file, an unknown preset, a slice outside the
  volume, an unstable time step). The CLI prints one ``error:`` line and exits with code 2.
- :class:`SimulationError`: the simulation itself failed (a non-finite value, a particle leaving the
  grid). The CLI prints one ``simulation error:`` line and exits with code 3.
"""

__all__ = ["InputError", "InputWarning", "SimulationError", "check_input_file", "strict_json", "optional"]


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


def strict_json(obj):
    """``obj`` made strict JSON (RFC 8259 has no NaN or Infinity, and strict readers refuse them): every non-finite
    number becomes null, and a dict holding one gains ``"<key>_null_reason"`` beside it ("not a number: undefined
    here", "infinite"). numpy scalars and arrays become plain numbers and lists; objects with ``to_json()`` their
    dict; anything else its string."""
    import math

    def why(x: float) -> str:
        return "not a number: undefined for this run" if math.isnan(x) else "infinite"

    def conv(o):
        if hasattr(o, "to_json") and not isinstance(o, type):
            return conv(o.to_json())
        if isinstance(o, dict):
            out = {}
            for k, v in o.items():
                v = conv(v)
                key = str(k)
                if isinstance(v, _Undefined):
                    out[key] = None
                    out[f"{key}_null_reason"] = v.reason
                else:
                    out[key] = v
            return out
        if isinstance(o, (list, tuple)):
            return [None if isinstance(v, _Undefined) else v for v in (conv(x) for x in o)]
        if hasattr(o, "tolist") and hasattr(o, "dtype"):  # numpy arrays and scalars
            return conv(o.tolist())
        if isinstance(o, bool) or o is None or isinstance(o, (int, str)):
            return o
        if isinstance(o, float):
            return o if math.isfinite(o) else _Undefined(why(o))
        return str(o)

    out = conv(obj)
    return None if isinstance(out, _Undefined) else out


class _Undefined:
    """A non-finite number on its way to null (:func:`strict_json`)."""

    def __init__(self, reason: str):
        self.reason = reason


#: the optional packages and the extra of ``pip install warpmpm[EXTRA]`` that brings each (pyproject.toml)
EXTRAS = {"xgboost": "models", "optuna": "models", "distributed": "sweeps", "rerun": "viewer"}


def optional(module: str, feature: str):
    """Import an optional dependency for ``feature``; :class:`InputError` saying which extra to install when absent."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        extra = EXTRAS.get(top, "all")
        raise InputError(f"{feature} needs the optional package {top!r}, which is not installed: pip install "
                         f"'warpmpm[{extra}]' (or bash scripts/setup.sh, which installs everything)") from None
