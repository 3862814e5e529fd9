"""warpmpm: 2D slice-driven multi-organ MPM estimation of 3D pancreas motion (NVIDIA Warp).

Data flows one way: images and labels (:mod:`warpmpm.images`, :mod:`warpmpm.phantom`) -> particle
model (:mod:`warpmpm.model`) -> solver (:mod:`warpmpm.kernels`, :mod:`warpmpm.solver`) <- driving
(:mod:`warpmpm.driving`) <- targets (:mod:`warpmpm.targets`) <- registration
(:mod:`warpmpm.registration`), with the slice and its in-plane motion in :mod:`warpmpm.slices`.
Beside it: ground truth (:mod:`warpmpm.groundtruth`), metrics (:mod:`warpmpm.metrics`), condition
selection (:mod:`warpmpm.selection`). On top: the experiment layer (:mod:`warpmpm.experiment`) and
the CLI (:mod:`warpmpm.cli`). The viewer (:mod:`warpmpm.viewer`) only reads, through the
:class:`warpmpm.recorder.Recorder` interface.
"""

__version__ = "0.1.0"

from .errors import InputError, SimulationError  # noqa: F401
from .images import COMBINATIONS, ORGANS, PRESETS, Case, Geometry, load_case, parse_organs  # noqa: F401
from .model import PAPER_MATERIALS, Material, ParticleModel, build_model, voxelize  # noqa: F401
from .phantom import PhantomConfig, make_phantom  # noqa: F401
from .slices import DrivingSlice, InPlaneAffine  # noqa: F401
