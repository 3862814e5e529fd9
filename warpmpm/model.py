"""The multi-organ particle model and the organ materials.

One particle per labelled voxel of each selected organ (the paper's choice), at the voxel's
centre in world coordinates (mm). A sampling step ``s > 1`` keeps every s-th voxel in-plane
(x and y; every slice is kept so that every axial slice still carries particles) and gives each
particle ``s * s`` voxel volumes.

Thick slices. Clinical scans are often 0.5-1.5 mm in-plane and 3-6 mm between slices. Particles on
such a voxel grid form sheets far apart along the slice normal, and a grid cell derived from the
particle volume is smaller than the gap between them: the sheets would not couple. When the gaps
between neighbouring particles differ by more than :data:`MAX_LATTICE_ANISOTROPY` (or with
``lattice="isotropic"``), the particles are laid on an isotropic lattice instead, of spacing
``h = (s_x s_y s_z step^2)^(1/3)`` (as many particles as the voxel sampling would give), inside each
organ's shape interpolated between slices (each organ's signed distance, linearly resampled, so a
thick-slice staircase does not become the anatomy). Slice indices keep naming the planning grid's
slices: a particle lies on slice ``k`` when it lies within that slice's thickness.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import SimpleITK as sitk

from .errors import InputError
from .images import ORGANS, Case, Geometry, orientation_image_axis, organs_to_letters, parse_organs

__all__ = ["Material", "PAPER_MATERIALS", "ParticleModel", "build_model", "MAX_LATTICE_ANISOTROPY",
           "lattice_geometry", "shape_based_labels", "voxelize"]


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
        geometry: the case grid the particles came from (slice indices name its slices).
        sampling_step: in-plane sampling step used on ``geometry`` (1 on an isotropic lattice).
        lattice: the isotropic grid whose voxel centres are the particles, when the scan's slices were
            too thick for the voxel grid (module docstring); None: the particles sit on ``geometry``.
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
    lattice: Geometry | None = None

    @property
    def particle_grid(self) -> Geometry:
        """The grid whose voxel centres the particles are (``lattice``, else ``geometry``)."""
        return self.lattice if self.lattice is not None else self.geometry

    @property
    def particle_spacing_mm(self) -> np.ndarray:
        """Distance between neighbouring particles along each image axis (mm)."""
        if self.lattice is not None:
            return np.asarray(self.lattice.spacing_mm, dtype=np.float64)
        return np.asarray(self.geometry.spacing_mm, dtype=np.float64) * np.array([self.sampling_step, self.sampling_step, 1])

    @property
    def max_gap_mm(self) -> float:
        """The largest gap between neighbouring particles (mm): no grid cell may be smaller."""
        return float(self.particle_spacing_mm.max())

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
        return replace(self, positions_mm=self.positions_mm[keep].copy(), organ_index=remap[self.organ_index[keep]].astype(np.int32),
                       organs=organs, voxel_ijk=self.voxel_ijk[keep].copy(), volume_mm3=self.volume_mm3[keep].copy(),
                       materials={o: self.materials[o] for o in organs}, meta=dict(self.meta))


def build_model(
    case: Case,
    organs: str | tuple[str, ...] = "psdl",
    sampling_step: int = 1,
    materials: dict[str, Material] | None = None,
    density_kg_m3: float | None = None,
    lattice: Literal["auto", "voxel", "isotropic"] = "auto",
) -> ParticleModel:
    """Build the particle model of ``organs`` from a case's label map.

    Args:
        case: the planning case (label map with geometry).
        organs: the paper's letters (``"psdl"``) or a tuple of organ names; pancreas always included.
        sampling_step: keep every s-th voxel along x and y (>= 1).
        materials: per-organ overrides of :data:`PAPER_MATERIALS`.
        density_kg_m3: one density for all organs (default: each material's, soft tissue 1040).
        lattice: ``voxel``: one particle per (sampled) voxel; ``isotropic``: an isotropic lattice inside
            the interpolated organ shapes (module docstring); ``auto`` (default): isotropic when the
            gaps between neighbouring voxel particles differ by more than :data:`MAX_LATTICE_ANISOTROPY`.
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
    if lattice not in ("auto", "voxel", "isotropic"):
        raise InputError(f"unknown particle lattice {lattice!r}; use auto, voxel or isotropic")
    gaps = np.asarray(case.geometry.spacing_mm) * np.array([sampling_step, sampling_step, 1])
    if lattice == "isotropic" or (lattice == "auto" and gaps.max() / gaps.min() > MAX_LATTICE_ANISOTROPY):
        return _build_on_isotropic_lattice(case, organs, sampling_step, {o: mats[o] for o in organs})
    pos, idx, ijk = [], [], []
    for n, organ in enumerate(organs):
        kk, jj, ii = np.nonzero(case.organ_mask(organ))
        if sampling_step > 1:
            keep = (ii % sampling_step == 0) & (jj % sampling_step == 0)
            if not keep.any():
                raise InputError(f"particle sampling step {sampling_step} leaves no particle of the {organ} "
                                 f"({len(ii)} voxels spanning {np.ptp(ii) + 1} x {np.ptp(jj) + 1} in-plane); use a smaller step")
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


#: Largest ratio between the gaps of neighbouring particles along the image axes kept on the voxel
#: grid: the phantom's 1.33 x 1.33 x 3 mm voxels (2.25) stay one particle per voxel; a 0.8 x 0.8 x 5 mm
#: CT (6.3) or a 1.5 x 1.5 x 6 mm MR (4) goes onto an isotropic lattice.
MAX_LATTICE_ANISOTROPY = 2.5


def lattice_geometry(geometry: Geometry, spacing_mm: float) -> Geometry:
    """An isotropic grid of ``spacing_mm`` over the same region and directions as ``geometry``."""
    extent = np.asarray(geometry.size) * np.asarray(geometry.spacing_mm)  # voxel faces to voxel faces
    size = np.maximum(1, np.round(extent / spacing_mm)).astype(int)
    # first lattice centre half a lattice cell inside the first voxel's outer face
    corner = geometry.index_to_world(np.full((1, 3), -0.5))[0]
    origin = corner + geometry.direction_matrix @ np.full(3, 0.5 * spacing_mm)
    return Geometry(tuple(int(v) for v in size), (float(spacing_mm),) * 3, tuple(float(v) for v in origin), geometry.direction)


def shape_based_labels(case: Case, organs, target: Geometry) -> np.ndarray:
    """Organ index map (z, y, x) on ``target`` (-1: none) from each organ's signed distance, resampled linearly.

    Interpolating the distance to each organ's surface between thick slices gives a smooth shape where
    nearest-neighbour resampling would give a staircase. A voxel claimed by two organs goes to the one
    it lies deeper inside.
    """
    ref = sitk.Image([int(v) for v in target.size], sitk.sitkFloat32)
    target.apply_to(ref)
    best = np.full(target.size[::-1], np.inf, dtype=np.float32)
    out = np.full(target.size[::-1], -1, dtype=np.int32)
    for n, organ in enumerate(organs):
        inside = case.organ_mask(organ)
        # signed distance to the organ's surface (negative inside), in mm. ITK's map is 0 on the outermost
        # organ voxels and one spacing on the first voxels outside; averaging it with the map of the
        # complement puts the zero half-way between them, where the voxel faces are, along every axis
        a, b = (sitk.SignedMaurerDistanceMap(case.geometry.apply_to(sitk.GetImageFromArray(m.astype(np.uint8))),
                                             insideIsPositive=False, squaredDistance=False, useImageSpacing=True)
                for m in (inside, ~inside))
        sdf = (a - b) * 0.5
        d = sitk.GetArrayFromImage(sitk.Resample(sdf, ref, sitk.Transform(), sitk.sitkLinear, 1e9, sitk.sitkFloat32))
        take = (d < best) & (d < 0)
        out[take] = n
        best = np.minimum(best, d)
    return out


def _build_on_isotropic_lattice(case: Case, organs, sampling_step: int, mats: dict[str, Material]) -> ParticleModel:
    h = float((case.geometry.voxel_volume_mm3 * sampling_step**2) ** (1.0 / 3.0))
    lat = lattice_geometry(case.geometry, h)
    labels = shape_based_labels(case, organs, lat)
    pos, idx = [], []
    for n, organ in enumerate(organs):
        kk, jj, ii = np.nonzero(labels == n)
        if len(ii) == 0:
            raise InputError(f"particle sampling step {sampling_step} leaves no particle of the {organ}: it is thinner than the "
                             f"{h:.2f} mm particle lattice this step gives; use a smaller step")
        p = lat.index_to_world(np.stack([ii, jj, kk], axis=1))
        pos.append(p)
        idx.append(np.full(len(p), n, dtype=np.int32))
    positions = np.concatenate(pos)
    # the planning voxel holding each particle: slice k of the scan holds the particles within its thickness
    voxel_ijk = np.rint(case.geometry.world_to_index(positions)).astype(np.int64)
    voxel_ijk = np.clip(voxel_ijk, 0, np.asarray(case.geometry.size) - 1).astype(np.int32)
    return ParticleModel(positions, np.concatenate(idx), tuple(organs), voxel_ijk, np.full(len(positions), h**3), mats,
                         case.geometry, 1, {"case": case.name, "lattice_mm": h}, lattice=lat)


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
