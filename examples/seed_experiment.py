"""The seed's experiment on one case: its MPM-made truth, the slice-driven estimate, baselines, table (``warpmpm run``).

    python examples/seed_experiment.py                      # built-in phantom, psdl, paper deformation 1
    python examples/seed_experiment.py --labels ../shared/data/totalseg_mr/labels.nii.gz \
        --image ../shared/data/totalseg_mr/image.nii.gz --preset totalseg_mr --json out.json

See ``python examples/seed_experiment.py --help`` for every option. The main job is ``examples/run_case.py``.
"""



from warpmpm.cli import run_main

if __name__ == "__main__":
    import sys

    # the seed's method is the estimate here (a later --estimator on the command line wins)
    raise SystemExit(run_main(["--estimator", "slice-driven", *sys.argv[1:]]))
