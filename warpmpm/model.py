"""The multi-organ particle model and the organ materials.

One particle per labelled voxel of each selected organ (the paper's choice), at the voxel's
centre in world coordinates (mm). A sampling step ``s > 1`` keeps every s-th voxel in-plane
(x and y; every slice is kept so that every axial slice still carries particles) and gives each
particle ``s * s`` voxel volumes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .images import ORGANS, Case, Geometry, organs_to_letters, parse_organs
from .slices import orientation_image_axis


@dataclass(frozen=True)
class Material:
    """Isotropic fixed-corotated material.

    Attributes:
        lam_pa: first Lame parameter lambda (Pa).
        mu_pa: shear modulus mu (Pa).
        density_kg_m3: physical density (kg/m^3).
    """

    lam_pa: float
    mu_pa: float
    density_kg_m3: float = 1040.0

    @property
    def youngs_modulus_pa(self) -> float:
        return self.mu_pa * (3 * self.lam_pa + 2 * self.mu_pa) / (self.lam_pa + self.mu_pa)

    @property
    def p_wave_modulus_pa(self) -> float:
        return self.lam_pa + 2 * self.mu_pa

    def wave_speed_m_s(self, density_kg_m3: float | None = None) -> float:
        rho = self.density_kg_m3 if density_kg_m3 is None else density_kg_m3
        return float(np.sqrt(self.p_wave_modulus_pa / rho))


#: The paper's material table (Table "Parameters of simulation"); density: soft tissue.
PAPER_MATERIALS: dict[str, Material] = {
    "pancreas": Material(lam_pa=5.76e4, mu_pa=1.17e3),
    "stomach": Material(lam_pa=8.32e7, mu_pa=1.68e5),
    "duodenum": Material(lam_pa=8.11e7, mu_pa=3.38e6),
    "left_kidney": Material(lam_pa=3.99e6, mu_pa=8.01e3),
}

@dataclass
class ParticleModel:
    """Particles of the selected organs in world coordinates.

    Attributes:
        positions_mm: (N, 3) world positions in mm (planning state).
        organ_index: (N,) index into ``organs`` for every particle.
        organs: organ names in this model, in :data:`ORGANS` order.
        voxel_ijk: (N, 3) voxel index (i, j, k) of each particle in the case grid.
        volume_mm3: (N,) particle volume in mm^3.
        materials: organ -> :class:`Material` used for this model.
        geometry: the case grid the particles came from.
        sampling_step: in-plane sampling step used.
    """

    positions_mm: np.ndarray
    organ_index: np.ndarray
    organs: tuple[str, ...]
    voxel_ijk: np.ndarray
    volume_mm3: np.ndarray
    materials: dict[str, Material]
    geometry: Geometry
    sampling_step: int = 1
    meta: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.positions_mm.shape[0])

    @property
    def letters(self) -> str:
        return organs_to_letters(self.organs)

    def organ_slice(self, organ: str) -> np.ndarray:
        """Boolean mask of the particles of ``organ``."""
        if organ not in self.organs:
            raise InputError(f"organ {organ!r} is not in this model ({self.letters})")
        return self.organ_index == self.organs.index(organ)

    def counts(self) -> dict[str, int]:
        return {o: int(np.sum(self.organ_index == i)) for i, o in enumerate(self.organs)}

    def per_particle(self, attribute: str) -> np.ndarray:
        """Per-particle array of a material attribute (``lam_pa``, ``mu_pa``, ``density_kg_m3``)."""
        table = np.array([getattr(self.materials[o], attribute) for o in self.organs], dtype=np.float64)
        return table[self.organ_index]

    def mass_kg(self) -> np.ndarray:
        return self.per_particle("density_kg_m3") * self.volume_mm3 * 1e-9

    def center_mm(self) -> np.ndarray:
        return self.positions_mm.mean(axis=0)

    def slice_mask(self, orientation: str, index: int) -> np.ndarray:
        """Particles lying on the slice ``index`` (voxel index of the planning volume) of an orientation."""
        axis = orientation_image_axis(self.geometry, orientation)
        size = self.geometry.size[axis]
        if not (0 <= int(index) < size):
            raise InputError(f"{orientation} slice {index} is outside the volume (valid 0..{size - 1})")
        return self.voxel_ijk[:, axis] == int(index)

    def slice_counts(self, orientation: str) -> np.ndarray:
        """(n_slices, n_organs) particle counts per slice of an orientation, organs in ``self.organs`` order."""
        axis = orientation_image_axis(self.geometry, orientation)
        n_org = len(self.organs)
        flat = self.voxel_ijk[:, axis].astype(np.int64) * n_org + self.organ_index
        return np.bincount(flat, minlength=self.geometry.size[axis] * n_org).reshape(-1, n_org)

    def subset(self, organs) -> "ParticleModel":
        """The model restricted to ``organs`` (a sub-combination)."""
        organs = tuple(o for o in ORGANS if o in organs)
        keep = np.isin(self.organ_index, [self.organs.index(o) for o in organs])
        remap = np.full(len(self.organs), -1)
        for new, o in enumerate(organs):
            remap[self.organs.index(o)] = new
        return ParticleModel(
            self.positions_mm[keep].copy(), remap[self.organ_index[keep]].astype(np.int32), organs,
            self.voxel_ijk[keep].copy(), self.volume_mm3[keep].copy(), dict(self.materials), self.geometry,
            self.sampling_step, dict(self.meta),
        )


def build_model(
    case: Case,
    organs: str | tuple[str, ...] = "psdl",
    sampling_step: int = 1,
    materials: dict[str, Material] | None = None,
    density_kg_m3: float | None = None,
) -> ParticleModel:
    """Build the particle model of ``organs`` from a case's label map.

    Args:
        case: the planning case (label map with geometry).
        organs: the paper's letters (``"psdl"``) or a tuple of organ names; pancreas always included.
        sampling_step: keep every s-th voxel along x and y (>= 1).
        materials: per-organ overrides of :data:`PAPER_MATERIALS`.
        density_kg_m3: one density for all organs (default: each material's, soft tissue 1040).
    """
    if isinstance(organs, str):
        organs = parse_organs(organs)
    else:
        organs = tuple(o for o in ORGANS if o in organs)
        if "pancreas" not in organs:
            raise InputError("the organ combination must include the pancreas")
    if int(sampling_step) != sampling_step or sampling_step < 1:
        raise InputError(f"sampling step must be an integer >= 1, got {sampling_step!r}")
    case.check_organs(organs)
    mats = dict(PAPER_MATERIALS)
    if materials:
        for k in materials:
            if k not in ORGANS:
                raise InputError(f"unknown organ {k!r} in material overrides")
        mats.update(materials)
    if density_kg_m3 is not None:
        mats = {k: Material(m.lam_pa, m.mu_pa, float(density_kg_m3)) for k, m in mats.items()}
    pos, idx, ijk = [], [], []
    for n, organ in enumerate(organs):
        kk, jj, ii = np.nonzero(case.organ_mask(organ))
        if sampling_step > 1:
            keep = (ii % sampling_step == 0) & (jj % sampling_step == 0)
            kk, jj, ii = kk[keep], jj[keep], ii[keep]
        v = np.stack([ii, jj, kk], axis=1)
        ijk.append(v)
        pos.append(case.geometry.index_to_world(v))
        idx.append(np.full(len(v), n, dtype=np.int32))
    voxel_ijk = np.concatenate(ijk).astype(np.int32)
    volume = np.full(len(voxel_ijk), case.geometry.voxel_volume_mm3 * sampling_step**2)
    return ParticleModel(
        np.concatenate(pos), np.concatenate(idx), organs, voxel_ijk, volume, {o: mats[o] for o in organs},
        case.geometry, int(sampling_step), {"case": case.name},
    )


def voxelize(positions_mm: np.ndarray, geometry: Geometry, mask: np.ndarray | None = None, sampling_step: int = 1) -> np.ndarray:
    """Boolean (z, y, x) mask of the voxels of ``geometry`` containing at least one particle.

    Each particle marks the voxel nearest its position (rounding its continuous index), which
    gives back an organ's mask exactly for a model at rest with sampling step 1. With a sampling
    step s, a particle stands for an s x s in-plane block and marks that block.
    """
    pts = positions_mm if mask is None else positions_mm[mask]
    ijk = np.rint(geometry.world_to_index(pts)).astype(np.int64)
    if sampling_step > 1:
        offs = np.array([(a, b, 0) for a in range(sampling_step) for b in range(sampling_step)])
        ijk = (ijk[:, None, :] + offs[None, :, :]).reshape(-1, 3)
    size = np.asarray(geometry.size)
    inside = np.all((ijk >= 0) & (ijk < size), axis=1)
    ijk = ijk[inside]
    out = np.zeros(geometry.size[::-1], dtype=bool)
    out[ijk[:, 2], ijk[:, 1], ijk[:, 0]] = True
    return out
