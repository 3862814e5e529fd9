"""The ``warpmpm`` command: ``run | sweep | sweep-planes | train-planes | plan-planes | multi | train | view | track |
estimators | make-cine | make-truth | evaluate-track | cine-info``.

    warpmpm run                                  # the seed's experiment on the built-in phantom (= examples/seed_experiment.py)
    warpmpm run --labels L.nii.gz --image I.nii.gz --preset totalseg_mr --json out.json --rrd out.rrd
    warpmpm sweep --phantom-seeds 0,1 --organs all --out runs/sweep.csv --workers 2
    warpmpm sweep-planes --phantom-seeds 0,1 --truth-seeds 0,1 --out runs/planes.csv --workers 2
    warpmpm train-planes runs/planes.csv --out runs/plane_placement.json
    warpmpm plan-planes --image I.nii.gz --labels L.nii.gz --preset totalseg_mr --picture planes.png
    warpmpm multi --phantom-seeds 0,1 --out runs/multi.csv
    warpmpm train runs/sweep.csv --out runs/selection_error.json
    warpmpm view out.rrd [--summary | --screenshot out.png]
    warpmpm make-cine --out runs/cine --frames 8                  # a synthetic series with its truth
    warpmpm track --image I --labels L --cine runs/cine/cine --out runs/track
    warpmpm evaluate-track --track runs/track --truth runs/cine/truth
    warpmpm estimators                                           # the tracker's estimators, what each measured

Exit codes: 0 success; 1 some sweep tasks failed (their rows are missing; re-run to retry); 2 bad
input, or a file the system would not read or write (one ``error:`` line naming it, nothing written); 3 the
simulation failed; 4 an error warpmpm did not foresee (one ``internal error:`` line, nothing written: a bug, please
report it; ``--verbose`` prints where it happened); 130 interrupted (Ctrl-C: one line saying what was kept); 141 standard output closed by its reader (``| head``: no traceback,
and what was still to be written may be missing, as with a shell's SIGPIPE).
"""

from __future__ import annotations

import os
import sys

from ..errors import InputError, SimulationError
from .exit_codes import EXIT_INPUT, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_PIPE_CLOSED, EXIT_SIMULATION, EXIT_TASKS_FAILED
from .experiment_commands import cmd_multi, cmd_run, cmd_sweep, cmd_sweep_planes, cmd_train, cmd_view, config_from_args
from .options import build_parser
from .plane_commands import cmd_plan_planes, cmd_train_planes
from .track_commands import cmd_cine_info, cmd_estimators, cmd_evaluate_track, cmd_make_cine, cmd_make_truth, cmd_track

__all__ = ["build_parser", "config_from_args", "cmd_run", "cmd_sweep", "cmd_sweep_planes", "cmd_plan_planes", "cmd_train_planes", "cmd_multi", "cmd_train", "cmd_view", "EXIT_INTERNAL",
           "cmd_track", "cmd_make_cine", "cmd_make_truth", "cmd_evaluate_track", "cmd_cine_info", "COMMANDS", "main", "run_main",
           "EXIT_TASKS_FAILED", "EXIT_INPUT", "EXIT_SIMULATION", "EXIT_INTERRUPTED", "EXIT_PIPE_CLOSED"]


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    return f"warning: {message}\n"


def _quiet(verbose: bool) -> None:
    """Show only what the user asked for: no Warp banner or module-load lines, no ITK warnings; our own
    warnings as one ``warning:`` line each."""
    import warnings

    import warp as wp

    if not verbose:
        warnings.formatwarning = _one_line_warning

    wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_ERROR
    if verbose:
        return
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    from ..experiment.tasks import init_warp_muted

    init_warp_muted()


COMMANDS = {"run": cmd_run, "cine-info": cmd_cine_info, "sweep": cmd_sweep, "sweep-planes": cmd_sweep_planes, "plan-planes": cmd_plan_planes,
            "train-planes": cmd_train_planes, "multi": cmd_multi, "train": cmd_train, "view": cmd_view, "track": cmd_track,
            "make-cine": cmd_make_cine, "estimators": cmd_estimators, "make-truth": cmd_make_truth, "evaluate-track": cmd_evaluate_track}


def main(argv=None) -> int:
    """Entry point of the ``warpmpm`` console script; returns the exit code (module docstring)."""
    a = build_parser().parse_args(argv)
    _quiet(getattr(a, "verbose", False))
    try:
        return COMMANDS[a.command](a)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except SimulationError as exc:
        print(f"simulation error: {exc}", file=sys.stderr)
        return EXIT_SIMULATION
    except KeyboardInterrupt:  # the resumable sweeps say themselves what they kept
        print("interrupted: nothing was written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # the reader of stdout went away (`warpmpm ... | head`): stop without a traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_PIPE_CLOSED
    except OSError as exc:  # the system refused a file (permissions, a full disk, a special file): name it
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: {where}{exc.strerror or exc}; check that the file exists, is a regular file and that you may read it "
              "(or write its folder)", file=sys.stderr)
        return EXIT_INPUT
    except Exception as exc:  # not foreseen: one line, never a traceback (--verbose prints it)
        if getattr(a, "verbose", False):
            import traceback

            traceback.print_exc()
        print(f"internal error: {type(exc).__name__}: {exc}. This is a bug in warpmpm, not in your input as far as it "
              "checked: please report it with the command (--verbose prints where it happened)", file=sys.stderr)
        return EXIT_INTERNAL


def run_main(argv=None) -> int:
    """``warpmpm run`` with ``argv`` (what ``examples/seed_experiment.py`` calls)."""
    return main(["run", *(sys.argv[1:] if argv is None else argv)])

