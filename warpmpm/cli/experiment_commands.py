"""The seed experiment's commands: ``run``, ``sweep``, ``multi``, ``train``, ``view``."""

from __future__ import annotations

import os
import sys
from dataclasses import replace

from ..errors import InputError

from .exit_codes import EXIT_TASKS_FAILED

__all__ = ["config_from_args", "cmd_run", "cmd_sweep", "cmd_sweep_planes", "cmd_multi", "cmd_train", "cmd_view"]


def config_from_args(a):
    """The :class:`~warpmpm.experiment.config.CaseConfig` of ``warpmpm run``'s options (checked)."""
    from ..experiment.config import CaseConfig
    from ..solvers import ExplicitConfig, SolverConfig

    step = a.particle_step if a.particle_step is not None else (2 if a.labels is None else 1)
    baselines = ("initial", "propagate", "rigid", "completion", "slice-driven") + (
        () if a.no_volume_registration else ("volume_registration",))
    protocol = "field" if a.truth_field is not None else a.protocol
    return CaseConfig(image=a.image, labels=a.labels, preset=a.preset, phantom_seed=a.phantom_seed, phantom_resolution=a.phantom_resolution,
                      estimator=a.estimator, materials=a.materials, organs=a.organs, slices=a.slices, protocol=protocol, truth_field=a.truth_field, deformation=a.deformation, targets=a.targets, drive=a.drive,
                      cine_thickness_mm=a.cine_thickness_mm, cine_linear_prior=a.cine_linear_prior, registration=a.registration, registration_passes=a.registration_passes, plane_check=not a.no_plane_check,
                      device=a.device, particle_step=step, lattice=a.lattice, perturb=not a.no_perturb, literal=a.literal_angles, max_steps=a.max_steps, wait_settled=a.wait_settled,
                      baselines=baselines, rrd_every=a.rrd_every, gt_contact=a.gt_contact, gt_wait_settled=a.gt_wait_settled,
                      solver=SolverConfig(method=a.solver, cpu_threads=a.threads, explicit=ExplicitConfig(contact=a.contact, friction=a.friction)))


def cmd_run(a) -> int:
    from ..experiment.auto import auto_condition
    from ..experiment.io import check_output_path, write_json_atomic
    from ..experiment.run import run_case
    from ..experiment.tables import format_table

    cfg = config_from_args(a)
    inputs = [("--labels", a.labels), ("--image", a.image), ("--truth-field", getattr(a, "truth_field", None))]
    for path, option in ((a.json, "--json"), (a.rrd, "--rrd")):
        if path:
            check_output_path(path, option, inputs)
    selection = None
    if cfg.is_auto:
        organs, slices, selection = auto_condition(cfg, a.selector, a.plane_selector)
        cfg = replace(cfg, organs=organs, slices=slices)
    recorder = None
    if a.rrd:
        from ..errors import optional

        optional("rerun", "a Rerun recording (--rrd)")
        from viewer.recording import RerunRecorder

        recorder = RerunRecorder(a.rrd, every=cfg.rrd_every)
    from ..experiment.run import Progress

    def tell(text, end="\n"):
        print(text, end=end, file=sys.stderr, flush=True)

    out = run_case(cfg, recorder, Progress(None if a.quiet else tell, live=sys.stderr.isatty()))
    out.selection = selection
    print(format_table(out))
    if selection is not None:
        print(f"selected {out.organs} {','.join(out.slices)} in {selection['selection_ms']:.2f} ms "
              f"(predicted {selection['predicted']:.2f})")
    if a.json:
        write_json_atomic(a.json, out)
        print(f"wrote {a.json}")
    if a.rrd:
        print(f"wrote {a.rrd} (open with: warpmpm view {a.rrd})")
    return 0


def _tasks_common(a):
    from ..experiment.sweep import sweep_cases

    if a.workers < 1:
        raise InputError(f"--workers must be at least 1, got {a.workers}")
    try:
        deformations = [int(x) for x in a.deformations.split(",")]
    except ValueError:
        raise InputError(f"--deformations must be comma-separated integers, got {a.deformations!r}") from None
    cases = sweep_cases(a.labels, a.image, a.preset, a.phantom_seeds, a.phantom_resolution)
    return cases, deformations


def _resumable(out_csv: str, run):
    """``run()``; on Ctrl-C one line saying what is kept (the rows finished so far stay in ``out_csv``) and exit 130."""
    try:
        return run()
    except KeyboardInterrupt:
        from ..experiment.io import read_rows
        from .exit_codes import EXIT_INTERRUPTED

        try:
            n = len(read_rows(out_csv))
        except (InputError, OSError):
            n = None
        kept = f"the {n} rows finished so far are kept in {out_csv}" if n else f"no row was written to {out_csv}"
        print(f"interrupted: {kept}; run the same command again to resume", file=sys.stderr)
        return EXIT_INTERRUPTED


def _write_table(out_csv: str, table: str) -> None:
    from ..experiment.io import check_output_path

    path = os.path.splitext(check_output_path(out_csv, "--out"))[0] + ".md"
    tmp = path + ".part"
    with open(tmp, "w") as f:
        f.write(table + "\n")
    os.replace(tmp, path)


def cmd_sweep(a) -> int:
    from ..experiment.config import CaseConfig
    from ..experiment.sweep import sweep
    from ..experiment.tables import summarize
    from ..images import COMBINATIONS

    if a.slice_stride < 1:
        raise InputError(f"--slice-stride must be at least 1, got {a.slice_stride}")
    cases, deformations = _tasks_common(a)
    combos = COMBINATIONS if a.organs == "all" else tuple(a.organs.split(","))
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    base = CaseConfig(estimator="slice-driven", particle_step=1 if a.particle_step is None else a.particle_step, lattice=a.lattice, device=a.device, targets=a.targets, drive=a.drive, max_steps=a.max_steps,
                      exclude_driven=True if a.exclude_driven else None)
    for combo in combos:
        replace(base, organs=combo)  # each combination checked before any task starts
    done = _resumable(a.out, lambda: sweep(cases, deformations, combos, tuple(a.orientations.split(",")), a.out,
                                           protocol=a.protocol, slice_stride=a.slice_stride, base=base, scheduler=a.scheduler,
                                           workers=a.workers))
    if isinstance(done, int):
        return done
    rows, failed = done
    table = summarize(rows)
    print(table)
    _write_table(a.out, table)
    return EXIT_TASKS_FAILED if failed else 0


def cmd_sweep_planes(a) -> int:
    """``warpmpm sweep-planes``: the plane-placement sweep on finite-element truths."""
    from ..experiment.io import check_output_path
    from ..experiment.plane_sweep import sweep_planes
    from ..experiment.sweep import sweep_cases

    cases = sweep_cases(a.labels, a.image, a.preset, a.phantom_seeds, a.phantom_resolution)
    try:
        seeds = [int(s) for s in a.truth_seeds.split(",")]
    except ValueError:
        raise InputError(f"--truth-seeds must be comma-separated integers, got {a.truth_seeds!r}") from None
    step = a.particle_step if a.particle_step is not None else (2 if a.labels is None else 1)
    out = check_output_path(a.out, "--out")
    if a.refresh_features:
        from ..experiment.plane_sweep import refresh_features

        n = refresh_features(out, cases, step, progress=lambda m: print(m, file=sys.stderr))
        print(f"{n} rows of {out} refreshed with today's placement features")
        return 0
    done = _resumable(out, lambda: sweep_planes(cases, seeds, [x for x in a.loads.split(",") if x],
                                                tuple(f for f in a.families.split(",") if f), a.positions, out,
                                                truth_cell_mm=a.truth_cell_mm, particle_step=step, scheduler=a.scheduler,
                                                workers=a.workers, progress=lambda m: print(m, file=sys.stderr)))
    if isinstance(done, int):
        return done
    rows, failed = done
    done = [r for r in rows if not r.get("failure")]
    print(f"{len(done)} placements scored in {out}" + (f"; {len(failed)} tasks failed" if failed else ""))
    return EXIT_TASKS_FAILED if failed else 0


def cmd_multi(a) -> int:
    from ..experiment.config import CaseConfig
    from ..experiment.multi_direction import multi_direction
    from ..experiment.tables import summarize_multi
    from ..selection import DEFAULT_PLANE_SELECTOR, DEFAULT_SELECTOR

    if a.top < 1:
        raise InputError(f"--top must be at least 1, got {a.top}")
    cases, deformations = _tasks_common(a)
    d = os.path.dirname(os.path.abspath(a.out))
    if not os.path.isdir(d):
        raise InputError(f"output folder {d} for --out does not exist")
    base = CaseConfig(estimator="slice-driven", particle_step=1 if a.particle_step is None else a.particle_step, lattice=a.lattice, device=a.device,
                      protocol=a.protocol)
    done = _resumable(a.out, lambda: multi_direction(cases, deformations, a.selector or DEFAULT_SELECTOR,
                                                     a.plane_selector or DEFAULT_PLANE_SELECTOR, a.out, base=base, top=a.top,
                                                     workers=a.workers, scheduler=a.scheduler))
    if isinstance(done, int):
        return done
    rows, failed = done
    table = summarize_multi(rows)
    print(table)
    _write_table(a.out, table)
    return EXIT_TASKS_FAILED if failed else 0


def cmd_train(a) -> int:
    from ..experiment.train import train

    return train(a)


def cmd_view(a) -> int:
    from ..errors import optional

    optional("rerun", "warpmpm view")
    from viewer.__main__ import main as view_main

    argv = [a.rrd] + (["--summary"] if a.summary else []) + (["--screenshot", a.screenshot] if a.screenshot else [])
    return view_main(argv)
