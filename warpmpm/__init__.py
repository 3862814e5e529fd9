"""warpmpm: 2D slice-driven multi-organ MPM estimation of 3D pancreas motion (NVIDIA Warp).

Data flows one way: labels (:mod:`warpmpm.images`, :mod:`warpmpm.phantom`) -> particle model
(:mod:`warpmpm.model`) -> solver (:mod:`warpmpm.kernels`, :mod:`warpmpm.solver`) <- driving
(:mod:`warpmpm.driving`) <- registration (:mod:`warpmpm.registration`); metrics
(:mod:`warpmpm.metrics`) and the viewer only read. :mod:`warpmpm.groundtruth` makes pseudo ground
truth and :mod:`warpmpm.runner` runs experiments.
"""

__version__ = "0.1.0"

from .images import ORGANS, PRESETS, Case, Geometry, InputError, load_case, parse_organs  # noqa: F401
from .model import PAPER_MATERIALS, Material, ParticleModel, build_model, voxelize  # noqa: F401
from .phantom import PhantomConfig, make_phantom  # noqa: F401
