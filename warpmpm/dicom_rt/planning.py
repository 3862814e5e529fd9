"""A planning case from a DICOM series and its RT Structure Set (:func:`case_from_rtstruct`)."""

from __future__ import annotations

import os

import numpy as np
import SimpleITK as sitk

from ..errors import InputError
from ..images import Geometry
from .rtstruct import find_structures, read_rtstruct
from .series import read_series_reference

__all__ = ["case_from_rtstruct"]


def case_from_rtstruct(image_folder: str, rtstruct: str, mapping: dict[str, str] | None = None, organs: str = "psdl"):
    """A :class:`~warpmpm.images.Case` from a DICOM planning series and its RT Structure Set.

    The organs are found by name (:func:`find_structures`; ``mapping`` organ -> ROI name first) and rasterised on the
    series' grid, labelled with the AMOS values (3 left kidney, 7 stomach, 10 pancreas, 13 duodenum). A voxel in two
    organs' contours goes to the first of pancreas, duodenum, stomach, left kidney (a warning gives the counts).
    ``case.meta["dicom"]`` keeps the series reference and ``case.meta["roi_names"]`` each organ's ROI name.
    Raises :class:`InputError` naming the organ, the structure or the frame of reference that is wrong.
    """
    import warnings

    from ..errors import InputWarning
    from ..images import PRESETS, Case, read_volume

    from ..errors import check_input_file

    check_input_file(rtstruct, "structure set", "give the planning RT Structure Set (RS*.dcm)")
    if not os.path.isdir(image_folder):
        raise InputError(f"--rtstruct needs the planning image as a DICOM series folder (--image FOLDER); {image_folder} is not a folder")
    ref = read_series_reference(image_folder)
    image = read_volume(image_folder)
    geometry = Geometry.of(image)
    ref.geometry = geometry
    from .rtstruct import _read_structure_set, _roi_names

    names = list(_roi_names(_read_structure_set(rtstruct), rtstruct).values())
    letters = {"p": "pancreas", "s": "stomach", "d": "duodenum", "l": "left_kidney"}
    wanted = [letters[c] for c in organs if c in letters]
    found = find_structures(names, mapping, organs=tuple(letters.values()))
    missing = [o for o in wanted if o not in found]
    if missing:
        leave = ("the pancreas is always modelled" if missing[0] == "pancreas" else "or leave the organ out with --organs")
        raise InputError(f"the structure set {rtstruct} has no structure for {', '.join(missing)} (it holds: {', '.join(names)}); "
                         f"name it with --structure {missing[0]}=NAME; {leave}")
    own_frame = "FrameOfReferenceUID" not in ref.extra.get("generated_uids", ())  # else nothing to check it against
    masks = read_rtstruct(rtstruct, geometry, ref.frame_of_reference_uid if own_frame else None, rois=[found[o] for o in wanted])
    label_map = dict(PRESETS["amos"])
    labels = np.zeros(tuple(geometry.size[::-1]), dtype=np.int32)
    overlaps = []
    for organ in ("pancreas", "duodenum", "stomach", "left_kidney"):
        if organ not in wanted:
            continue
        m = masks.get(found[organ])
        if m is None:
            raise InputError(f"structure {found[organ]!r} ({organ}) in {rtstruct} has no contours; draw it in the planning system")
        if not m.any():
            raise InputError(f"structure {found[organ]!r} ({organ}) in {rtstruct} covers no voxel of the planning image")
        taken = m & (labels > 0)
        if taken.any():
            overlaps.append(f"{int(taken.sum())} voxels of {found[organ]!r}")
        labels[m & (labels == 0)] = label_map[organ]
    if overlaps:
        warnings.warn(f"structures overlap; the overlapping voxels go to the organ first in pancreas, duodenum, stomach, left "
                      f"kidney: {', '.join(overlaps)}", InputWarning, stacklevel=2)
    arr = sitk.GetArrayFromImage(image).astype(np.float32)
    case = Case(labels, geometry, {o: label_map[o] for o in wanted}, arr, os.path.basename(os.path.normpath(image_folder)),
                f"{image_folder} + {rtstruct}")
    case.meta["dicom"] = ref
    case.meta["roi_names"] = {o: found[o] for o in wanted}
    return case
