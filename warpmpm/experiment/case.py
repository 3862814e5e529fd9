"""A planning case prepared for experiments: read or generated, cropped to its organs, modelled once.

The crop changes voxel indices: a user names slices by the input volume's indices, the particle model
works in the crop's. :class:`PreparedCase` holds the offset and is the one place that converts
between the two (:meth:`PreparedCase.to_crop`, :meth:`PreparedCase.to_input`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..images import ORGANS, Case, crop_to_organs, load_case, parse_organs
from ..model import ParticleModel, build_model
from ..phantom import make_phantom
from ..slices import DrivingSlice, parse_slices
from .config import CaseConfig

__all__ = ["PreparedCase", "prepare_case"]


@dataclass
class PreparedCase:
    """A case cropped to its organs with its full (all-organ) particle model.

    Attributes:
        case: the cropped case (labels, image, geometry of the crop).
        offset: (i, j, k) voxel offset of the crop in the input volume (input index = crop index + offset).
        input_centre_mm: world centre of the input volume (the paper's centre of the slice affines).
        full_model: particles of every organ of the method present in the label map.
        input_size: (i, j, k) size of the input volume.
    """

    case: Case
    offset: tuple[int, int, int]
    input_centre_mm: np.ndarray
    full_model: ParticleModel
    input_size: tuple[int, int, int] = (0, 0, 0)

    @property
    def input_geometry(self):
        """The grid of the whole input volume (before the crop)."""
        lo = tuple(-int(o) for o in self.offset)
        return self.case.geometry.crop(lo, tuple(a + int(n) for a, n in zip(lo, self.input_size)))

    @property
    def centre_mm(self) -> np.ndarray:
        """The centre of the in-plane motions (the input volume's centre)."""
        return self.input_centre_mm

    def model(self, organs: str) -> ParticleModel:
        """The particle model of an organ combination (paper letters)."""
        return self.full_model.subset(parse_organs(organs))

    def to_input(self, s: DrivingSlice) -> DrivingSlice:
        """A slice of the crop as the input volume's slice."""
        return s.shifted(self.offset[s.image_axis(self.case.geometry)])

    def to_crop(self, s: DrivingSlice) -> DrivingSlice:
        """A slice of the input volume as the crop's slice; :class:`InputError` when it misses the crop."""
        axis = s.image_axis(self.case.geometry)
        if not (0 <= s.index < self.input_size[axis]):
            raise InputError(f"{s.orientation} slice {s.index} is outside the volume (valid 0..{self.input_size[axis] - 1})")
        local = s.shifted(-self.offset[axis])
        size = self.case.geometry.size[axis]
        if not (0 <= local.index < size):
            raise InputError(f"{s.orientation} slice {s.index} holds none of the organs in use "
                             f"(they span input indices {self.offset[axis]}..{self.offset[axis] + size - 1})")
        return local

    def label(self, orientation: str, k: int) -> str:
        """``"orientation:index"`` of the crop's slice ``k`` in input-volume indices (what users type)."""
        return str(self.to_input(DrivingSlice(orientation, int(k))))

    def resolve_slices(self, model: ParticleModel, text: str | None) -> list[DrivingSlice]:
        """Driving slices in the crop from input-volume indices (default: the mid-pancreas axial slice)."""
        if text is None or text == "":
            axis = DrivingSlice("axial", 0).image_axis(model.geometry)
            ks = model.voxel_ijk[model.organ_slice("pancreas"), axis]
            return [DrivingSlice("axial", int(np.median(ks)))]
        return [self.to_crop(s) for s in parse_slices(text)]


def prepare_case(cfg: CaseConfig) -> PreparedCase:
    """Read (or generate) the case, crop it to its organs plus 15 mm, and build the all-organ model."""
    if cfg.labels is None:
        case = make_phantom(seed=cfg.phantom_seed, resolution=cfg.phantom_resolution, preset=cfg.preset)
    else:
        case = load_case(cfg.labels, cfg.image, cfg.preset)
    organs = parse_organs(cfg.organs)
    case.check_organs(organs)
    # The GT scene holds every organ of the method present in the label map.
    present = tuple(o for o in ORGANS if o in case.label_map and np.any(case.labels == case.label_map[o]))
    input_centre = case.geometry.center_mm()
    cropped, offset = crop_to_organs(case, present, margin_mm=15.0)
    full = build_model(cropped, present, sampling_step=cfg.particle_step, lattice=cfg.lattice)
    return PreparedCase(cropped, offset, input_centre, full, case.geometry.size)
