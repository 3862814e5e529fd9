"""Run one whole case: ground truth, slice-driven estimate, baselines, table (the same as ``warpmpm run``).

    python examples/run_case.py                      # built-in phantom, psdl, paper deformation 1
    python examples/run_case.py --labels ../shared/data/totalseg_mr/labels.nii.gz \
        --image ../shared/data/totalseg_mr/image.nii.gz --preset totalseg_mr --json out.json

See ``python examples/run_case.py --help`` for every option.
"""

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from warpmpm.cli import run_main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(run_main())
