"""One set of defaults per product, written once: every subcommand's default is its config's (the seed's experiment:
CaseConfig, read by run and sweep; the tracker: TrackerConfig, read by track)."""

import dataclasses

from warpmpm.cli import build_parser
from warpmpm.experiment.config import CaseConfig
from warpmpm.tracker import TrackerConfig


def test_the_experiments_subcommands_take_caseconfigs_defaults():
    cfg = CaseConfig()
    p = build_parser()
    run = p.parse_args(["run"])
    sweep = p.parse_args(["sweep"])
    for a in (run, sweep):
        assert a.targets == cfg.targets and a.drive == cfg.drive and a.max_steps == cfg.max_steps
    assert run.registration == cfg.registration and run.registration_passes == cfg.registration_passes
    assert run.solver == cfg.solver.method and run.no_plane_check == (not cfg.plane_check)
    from warpmpm.cli import config_from_args

    built = config_from_args(run)  # what `warpmpm run` with no option runs
    for f in ("targets", "registration", "registration_passes", "drive", "max_steps", "plane_check", "organs", "deformation",
              "protocol", "exclude_driven", "rrd_every"):
        assert getattr(built, f) == getattr(cfg, f), f
    assert built.solver.method == cfg.solver.method and built.solver.explicit.contact == cfg.solver.explicit.contact


def test_the_trackers_subcommand_takes_trackerconfigs_defaults():
    cfg = TrackerConfig()
    a = build_parser().parse_args(["track", "--image", "i", "--labels", "l", "--cine", "c", "--out", "o"])
    assert a.max_steps == cfg.max_steps and a.solver == cfg.solver.method and a.registration == cfg.registration
    assert a.linear_prior == cfg.registration_linear_prior and a.reference == cfg.reference and a.organs == cfg.organs
    assert a.estimator == cfg.estimator == "copy"
    assert a.particle_step == cfg.particle_step and (not a.no_predict) == cfg.predict and a.wait_settled == cfg.wait_settled
    assert {f.name for f in dataclasses.fields(cfg)} >= {"max_steps", "registration", "reference", "predict"}
