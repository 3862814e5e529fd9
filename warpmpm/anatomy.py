"""The anatomy of a labelled planning scan that a model of the abdomen needs: the body outline, each voxel's tissue
class (the organs of the method, liver, bone where the preset labels vertebrae, else surrounding soft tissue), the
bones held still, and the published soft-tissue moduli.

Read by the finite-element truths (:mod:`warpmpm.truth_fem`) and by the estimator's completion solve
(:mod:`warpmpm.solvers.completion`): both model the same anatomy; neither uses the other's solver.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .images import ORGANS, Case

__all__ = ["TISSUES", "TISSUE_CODE", "TissueRange", "TISSUE_RANGES", "ANCHOR_LABELS", "LIVER_LABELS", "body_mask", "tissue_map",
           "nominal_material"]

#: Tissue classes of the mesh, in the order of their integer codes.
TISSUES = ("air", "soft_tissue", "pancreas", "stomach", "duodenum", "left_kidney", "liver", "bone")
#: Tissue name -> integer code.
TISSUE_CODE = {t: i for i, t in enumerate(TISSUES)}
_T = TISSUE_CODE


@dataclass(frozen=True)
class TissueRange:
    """A published range of a tissue's shear modulus (kPa) and Poisson's ratio, and where it comes from."""

    mu_kpa: tuple[float, float]
    nu: tuple[float, float]
    source: str


#: Published soft-tissue ranges the materials are drawn from (uniformly, per case). Shear moduli from in-vivo MR
#: elastography where it exists; Poisson's ratio 0.45-0.49 (nearly incompressible soft tissue).
TISSUE_RANGES: dict[str, TissueRange] = {
    "pancreas": TissueRange((1.0, 1.6), (0.45, 0.49),
                            "MR elastography, healthy volunteers: 1.15 +- 0.17 kPa at 40 Hz (Shi et al., J Magn Reson Imaging 2015;41:369)"),
    "liver": TissueRange((1.8, 2.6), (0.45, 0.49),
                         "MR elastography, healthy liver 2.20 +- 0.3 kPa at 60 Hz (Yin et al., Clin Gastroenterol Hepatol 2007;5:1207)"),
    "left_kidney": TissueRange((2.5, 4.5), (0.45, 0.49),
                               "MR elastography of healthy kidneys, about 3-4 kPa at 90 Hz (Rouviere et al., J Magn Reson Imaging 2011;34:880)"),
    "stomach": TissueRange((0.8, 2.0), (0.45, 0.49),
                           "hollow viscus with contents: no in-vivo elastography standard; drawn around the pancreas's range"),
    "duodenum": TissueRange((0.8, 2.0), (0.45, 0.49),
                            "hollow viscus with contents: no in-vivo elastography standard; drawn around the pancreas's range"),
    "soft_tissue": TissueRange((0.3, 1.0), (0.45, 0.49),
                               "fat and loose connective tissue, Young's modulus about 1-3 kPa (Comley & Fleck, Int J Solids Struct 2010;47:2982)"),
    "bone": TissueRange((20.0, 20.0), (0.3, 0.3),
                        "vertebrae: held (every node of a bone cell is fixed); the modulus only stiffens the tissue cells that "
                        "bone enters partly, 10-60x the soft tissue's (bone's own 10 GPa would only make the system stiff to solve)"),
}

#: Label values of bones the truth holds still (the spine), per preset; the posterior wall is held in every case.
ANCHOR_LABELS: dict[str, tuple[int, ...]] = {
    "amos": (),  # AMOS labels no bone
    "totalseg_mr": (18, 19),  # sacrum, vertebrae
    "totalseg_ct": tuple(range(25, 51)),  # sacrum, vertebrae S1..C1
}
#: Label of the liver per preset (a tissue of its own; without it the liver is surrounding soft tissue).
LIVER_LABELS: dict[str, int] = {"amos": 6, "totalseg_mr": 5, "totalseg_ct": 5}


def body_mask(case: Case) -> np.ndarray:
    """The body outline (z, y, x): the intensity image's foreground (Otsu threshold), its holes filled axial slice by
    slice (bowel gas, lungs), its largest connected part, joined with every labelled voxel. Without an image: the
    labelled voxels dilated by 15 mm."""
    import SimpleITK as sitk
    from scipy import ndimage

    lab = case.labels > 0
    if case.image is None:
        it = np.ceil(15.0 / np.asarray(case.geometry.spacing_mm[::-1])).astype(int)
        return ndimage.binary_dilation(lab, structure=np.ones(tuple(2 * it + 1), bool)) | lab
    img = case.geometry.apply_to(sitk.GetImageFromArray(case.image.astype(np.float32)))
    smooth = sitk.SmoothingRecursiveGaussian(img, float(max(case.geometry.spacing_mm)))
    fg = sitk.GetArrayFromImage(sitk.OtsuThreshold(smooth, 0, 1)).astype(bool)
    for k in range(fg.shape[0]):
        fg[k] = ndimage.binary_fill_holes(fg[k])
    comp, n = ndimage.label(fg)
    if n > 1:
        sizes = ndimage.sum(fg, comp, index=np.arange(1, n + 1))
        fg = comp == (1 + int(np.argmax(sizes)))
    return fg | lab


def tissue_map(case: Case, preset: str | None) -> np.ndarray:
    """(z, y, x) tissue codes (:data:`TISSUES`) of the scan's voxels."""
    out = np.where(body_mask(case), _T["soft_tissue"], _T["air"]).astype(np.int8)
    if preset in LIVER_LABELS and LIVER_LABELS[preset] not in case.label_map.values():
        out[case.labels == LIVER_LABELS[preset]] = _T["liver"]
    for v in ANCHOR_LABELS.get(preset or "", ()):
        if v not in case.label_map.values():
            out[case.labels == v] = _T["bone"]
    for organ in ORGANS:
        if organ in case.label_map:
            out[case.labels == case.label_map[organ]] = _T[organ]
    return out


def nominal_material(tissue: str) -> tuple[float, float]:
    """``(mu_pa, lam_pa)`` of a tissue at the middle of its published range (:data:`TISSUE_RANGES`): the shear
    modulus's and Poisson's ratio's midpoints."""
    r = TISSUE_RANGES[tissue]
    mu = 1e3 * 0.5 * (r.mu_kpa[0] + r.mu_kpa[1])
    nu = 0.5 * (r.nu[0] + r.nu[1])
    return mu, 2.0 * mu * nu / (1.0 - 2.0 * nu)
