"""What a synthetic experiment images: the planning volume and the same volume at the GT state.

A cine MR slice at the GT state is captured from the planning image warped by the GT's particle
motion (:func:`warpmpm.groundtruth.warp_image`); without an image both volumes are smooth organ
intensities drawn from the planning and GT label maps.
"""

from __future__ import annotations

import numpy as np

from ..groundtruth import GroundTruth
from ..imaging import warp_image
from ..images import Case
from ..imaging import organ_intensity_volume

__all__ = ["planning_and_gt_volumes"]


def planning_and_gt_volumes(case: Case, gt: GroundTruth) -> tuple[np.ndarray, np.ndarray]:
    """The planning intensity volume and the same at the GT state, (z, y, x) on the case grid.

    The GT warp is the costly part; it is computed once per GT and case and kept in ``gt.cache``.
    """
    cached = gt.cache.get("volumes")
    if cached is not None and cached[0] is case:
        return cached[1]
    if case.image is not None:
        pair = (case.image, warp_image(case, gt.model, gt.positions_mm))
    else:
        values = {o: case.label_map[o] for o in gt.model.organs}
        pair = (organ_intensity_volume(case.labels, values, case.geometry),
                organ_intensity_volume(gt.label_map(values), values, case.geometry))
    gt.cache["volumes"] = (case, pair)
    return pair
