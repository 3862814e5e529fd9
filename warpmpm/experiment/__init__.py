"""The experiment layer: runs the estimator on a planning case against a pseudo ground truth, beside the
baselines, one run at a time or as sweeps. It sits on top of the library and the library never imports it.

- :mod:`~warpmpm.experiment.config`: :class:`CaseConfig`, typed and checked once.
- :mod:`~warpmpm.experiment.case`: :class:`PreparedCase` (crop, full model, input <-> crop slice indices).
- :mod:`~warpmpm.experiment.truth`: the GT of a run; :mod:`~warpmpm.experiment.capture`: the GT-warped image.
- :mod:`~warpmpm.experiment.target_kinds`: the ``--targets`` kinds; :mod:`~warpmpm.experiment.baselines`: the baselines.
- :mod:`~warpmpm.experiment.run`: :func:`run_case`, :func:`run_prepared`; :mod:`~warpmpm.experiment.result`: what they return.
- :mod:`~warpmpm.experiment.sweep`, :mod:`~warpmpm.experiment.multi_direction`: the paper's sweeps;
  :mod:`~warpmpm.experiment.tasks`: running their tasks; :mod:`~warpmpm.experiment.io`: safe output;
  :mod:`~warpmpm.experiment.tables`: Markdown tables; :mod:`~warpmpm.experiment.auto`: ``--slices auto``.
"""

from .case import PreparedCase, prepare_case
from .config import CaseConfig
from .result import EstimateScores, RunResult, Scores
from .run import run_case, run_prepared
from .truth import make_ground_truth

__all__ = ["PreparedCase", "prepare_case", "CaseConfig", "EstimateScores", "RunResult", "Scores", "run_case", "run_prepared",
           "make_ground_truth"]
