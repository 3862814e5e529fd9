"""Test scenes: blocks of one organ's material and two models merged into one scene.

They are the scenes of the solver tests, the FEM comparison and the benchmarks; the planning models of
real cases come from :func:`warpmpm.model.build_model`.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .images import ORGANS, Geometry
from .model import PAPER_MATERIALS, Material, ParticleModel

__all__ = ["block_model", "merge_models", "inclusion_model"]


def block_model(
    shape: tuple[int, int, int],
    spacing_mm: tuple[float, float, float] = (2.0, 2.0, 2.0),
    organ: str = "pancreas",
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
    materials: dict[str, Material] | None = None,
) -> ParticleModel:
    """A rectangular block of one organ's material, one particle per voxel: the test scene.

    ``shape`` is the number of voxels along x, y, z; the block's grid is the volume itself.
    """
    geom = Geometry(tuple(int(s) for s in shape), tuple(float(s) for s in spacing_mm), tuple(float(o) for o in origin_mm))
    kk, jj, ii = np.meshgrid(*[np.arange(s) for s in shape[::-1]], indexing="ij")
    ijk = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], axis=1).astype(np.int32)
    mats = dict(PAPER_MATERIALS)
    mats.update(materials or {})
    return ParticleModel(geom.index_to_world(ijk), np.zeros(len(ijk), dtype=np.int32), (organ,), ijk,
                         np.full(len(ijk), geom.voxel_volume_mm3), {organ: mats[organ]}, geom)


def merge_models(a: ParticleModel, b: ParticleModel) -> ParticleModel:
    """Two models with different organs in one scene (test scenes of touching bodies), on one grid that covers both.

    The two must lie on one voxel lattice (the same spacing, directions and sampling step, their origins a whole number
    of voxels apart, no isotropic lattice); the merged grid is the box of both grids and every particle's voxel index is
    its index in it, so a slice index names the same plane for the particles of both and the grid's centre is the
    scene's."""
    organs = tuple(o for o in ORGANS if o in a.organs or o in b.organs)
    if set(a.organs) & set(b.organs):
        raise InputError("merge_models needs models of different organs")
    if a.lattice is not None or b.lattice is not None:
        raise InputError("merge_models takes models on their voxel grids, not on an isotropic lattice")
    ga, gb = a.geometry, b.geometry
    offset = ga.world_to_index(np.asarray(gb.origin_mm, dtype=np.float64)[None, :])[0]
    if (not np.allclose(ga.spacing_mm, gb.spacing_mm, rtol=1e-6) or not np.allclose(ga.direction, gb.direction, atol=1e-9)
            or not np.allclose(offset, np.rint(offset), atol=1e-3) or a.sampling_step != b.sampling_step):
        raise InputError("merge_models needs models on one voxel lattice: the same spacing, directions and sampling step, "
                         f"origins a whole number of voxels apart (spacing {ga.spacing_mm} and {gb.spacing_mm} mm, the second "
                         f"origin at voxel {np.round(offset, 3).tolist()} of the first grid)")
    offset = np.rint(offset).astype(np.int64)
    lo = np.minimum(0, offset)
    hi = np.maximum(np.asarray(ga.size), offset + np.asarray(gb.size))
    geometry = ga.crop(tuple(int(v) for v in lo), tuple(int(v) for v in hi))
    idx = np.concatenate([[organs.index(a.organs[i]) for i in a.organ_index], [organs.index(b.organs[i]) for i in b.organ_index]]).astype(np.int32)
    ijk = np.vstack([a.voxel_ijk - lo, b.voxel_ijk + offset - lo]).astype(np.int32)
    mats = {**a.materials, **b.materials}
    return ParticleModel(np.vstack([a.positions_mm, b.positions_mm]), idx, organs, ijk,
                         np.concatenate([a.volume_mm3, b.volume_mm3]), {o: mats[o] for o in organs}, geometry, a.sampling_step)


def inclusion_model(
    shape: tuple[int, int, int],
    box: tuple[tuple[int, int], tuple[int, int], tuple[int, int]],
    spacing_mm: tuple[float, float, float] = (2.0, 2.0, 2.0),
    matrix: str = "pancreas",
    inclusion: str = "duodenum",
    materials: dict[str, Material] | None = None,
) -> ParticleModel:
    """A block of ``matrix`` with the voxels of ``box`` (``((i0, i1), (j0, j1), (k0, k1))``, half-open voxel ranges)
    made of ``inclusion``: one lattice, one particle per voxel (so the FEM reference can mesh it). With the box away
    from a driven slice it is a stiff body hanging on a soft one, the case that sets how fast a whole abdomen settles
    (:mod:`warpmpm.solvers.rigid_modes`)."""
    if matrix == inclusion:
        raise InputError("inclusion_model needs two different organs")
    base = block_model(shape, spacing_mm, matrix, materials=materials)
    ijk = base.voxel_ijk
    inside = np.ones(base.n, dtype=bool)
    for axis, (lo, hi) in enumerate(box):
        if not (0 <= lo < hi <= shape[axis]):
            raise InputError(f"inclusion box {box} does not fit the block's {shape} voxels along axis {axis}")
        inside &= (ijk[:, axis] >= lo) & (ijk[:, axis] < hi)
    mats = dict(PAPER_MATERIALS)
    mats.update(materials or {})
    organs = tuple(o for o in ORGANS if o in (matrix, inclusion))
    idx = np.where(inside, organs.index(inclusion), organs.index(matrix)).astype(np.int32)
    return ParticleModel(base.positions_mm, idx, organs, ijk, base.volume_mm3, {o: mats[o] for o in organs}, base.geometry)
