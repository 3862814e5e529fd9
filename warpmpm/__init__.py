"""warpmpm: 2D slice-driven multi-organ MPM estimation of 3D pancreas motion (NVIDIA Warp).

Data flows one way: images and labels (:mod:`warpmpm.images`, :mod:`warpmpm.phantom`) -> particle
model (:mod:`warpmpm.model`) -> solver (:mod:`warpmpm.solvers.explicit_kernels`, :mod:`warpmpm.solvers`) <- driving
(:mod:`warpmpm.driving`) <- targets (:mod:`warpmpm.targets`) <- registration
(:mod:`warpmpm.registration`), with the slice and its in-plane motion in :mod:`warpmpm.slices`; the completion
solve of the whole abdomen in :mod:`warpmpm.solvers`, the anatomy it and the truths read in :mod:`warpmpm.anatomy`.
Beside it: ground truth (:mod:`warpmpm.groundtruth`), metrics (:mod:`warpmpm.metrics`), condition
selection (:mod:`warpmpm.selection`). On top: the experiment layer (:mod:`warpmpm.experiment`) and
the CLI (:mod:`warpmpm.cli`). The viewer (:mod:`viewer`, beside the package) only reads, through the
:class:`warpmpm.recorder.Recorder` interface.
"""

__version__ = "0.1.0"

from .errors import InputError, SimulationError  # noqa: F401
from .images import COMBINATIONS, ORGANS, PRESETS, Case, Geometry, load_case, parse_organs  # noqa: F401
from .model import PAPER_MATERIALS, Material, ParticleModel, build_model, voxelize  # noqa: F401
from .phantom import PhantomConfig, make_phantom  # noqa: F401
from .slices import DrivingSlice, InPlaneAffine  # noqa: F401

#: Names README uses from deeper modules, imported on first use (``import warpmpm`` stays light: no Warp kernels
#: are loaded until a solver is asked for).
_LAZY = {
    "CaseConfig": "warpmpm.experiment", "run_case": "warpmpm.experiment",
    "TruthConfig": "warpmpm.truth_fem", "make_truth": "warpmpm.truth_fem",
    "write_field": "warpmpm.fields", "read_field": "warpmpm.fields",
    "SliceDrivenEstimator": "warpmpm.driving", "affine_targets": "warpmpm.targets", "paper_affine": "warpmpm.groundtruth",
    "CompletionConfig": "warpmpm.solvers.completion", "CompletionModel": "warpmpm.solvers.completion",
    "complete": "warpmpm.solvers.completion",
    "track": "warpmpm.session", "TrackerConfig": "warpmpm.tracker", "ESTIMATORS": "warpmpm.estimators",
    "OUTPUTS": "warpmpm.outputs",
}

__all__ = ["InputError", "SimulationError", "COMBINATIONS", "ORGANS", "PRESETS", "Case", "Geometry", "load_case", "parse_organs",
           "PAPER_MATERIALS", "Material", "ParticleModel", "build_model", "voxelize", "PhantomConfig", "make_phantom",
           "DrivingSlice", "InPlaneAffine", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'warpmpm' has no attribute {name!r}")
