"""Finite-element truths of abdominal motion, made by a solver the estimator does not use.

A truth frame is the elastic equilibrium of the abdomen around the organs under anatomical loads, solved by
finite elements: small-strain linear elasticity on trilinear hexahedra (element matrices from scikit-fem,
selective reduced integration so that nearly incompressible tissue does not lock), assembled in numpy/scipy and
solved by a sparse direct factorisation or by conjugate gradients preconditioned with smoothed-aggregation
algebraic multigrid (``pyamg``). Nothing here calls the MPM.

The model (:func:`build_abdomen_mesh`):

- **Region**: a box around the organs of the method plus ``margin_mm`` (clipped to the scan), cut into cells of
  ``cell_mm`` along the scan's axes. A cell is tissue when most of it lies inside the body outline (the
  intensity image's foreground, holes filled slice by slice, joined with every labelled voxel); air outside the
  body is not meshed.
- **Tissues**: each cell is sampled at points about 1.5 mm apart; each point takes the tissue of its voxel
  (pancreas, stomach, duodenum, left kidney, liver, bone where the preset labels vertebrae, else surrounding soft
  tissue: fat and connective tissue). The cell's shear modulus is the harmonic mean of its points' (thin soft
  layers are not stiffened by the cell around them), its first Lame parameter the arithmetic mean.
- **Sliding**: organs slide along their neighbours through a *compliant interface layer*: the points within
  ``interface_mm / 2`` of another organ take a shear modulus ``interface_ratio`` times the softer side's (the
  loose areolar tissue and peritoneal fluid between viscera), keeping their bulk modulus. A layer rather than
  frictionless contact because it keeps the problem linear (one factorisation serves every frame, every frame is
  an exact equilibrium) and needs no conforming surface mesh, which a voxel label map does not give.
- **Materials** are drawn per case (``seed``) from published soft-tissue ranges (:data:`TISSUE_RANGES`), never from
  the estimator's table. All loads are kinematic (prescribed displacements and eigenstrains), so the answer
  depends only on the ratios of the moduli, not on their scale (MR elastography's dynamic moduli serve as well
  as quasi-static ones for that).
- **Anchors**: the patient lies supine on the couch: the most posterior tissue node of every column across the
  back (the posterior wall) is held, and so is every node of a bone cell (vertebrae where the preset labels them,
  :data:`ANCHOR_LABELS`).
- **Loads** (:data:`LOADS`), any combination:
  ``breathing``: the superior face (the diaphragm side) moves inferior by 8-20 mm and anterior by 2-5 mm at peak
  inhale, with a Lujan waveform ``sin^4(pi t / T)`` whose period (3.5-5 s), amplitude and exhale baseline
  (+-1.5 mm) are drawn per cycle; the motion fades to zero over ``posterior_taper_mm`` toward the held back
  (the crura of the diaphragm are tied to the spine).
  ``drift``: a slow superior-inferior drift of the diaphragm side, 0.05-0.2 mm/s inferior.
  ``filling``: the stomach swells (an isotropic eigenstrain growing linearly to a 5-15 % volume gain at the
  series' end).
  ``push``: a local swelling of the duodenum (the stomach when the case has no duodenum) where it touches the
  pancreas: a Gaussian bolus of 12-20 mm radius, 30-60 % volumetric eigenstrain at its centre (a bowel segment
  going from collapsed to distended), rising and falling over the series (``sin^2``).
  ``peristalsis``: a contraction band (-5 to -10 % volumetric eigenstrain, Gaussian of 12 mm) running along the
  duodenum's long axis at 5-15 mm/s (it forms over the first 0.5 s).
- **Frames**: frame ``n`` at ``t = n / fps``; frame 0 is the planning state (exhale) plus whatever the aperiodic
  loads hold at t = 0 (nothing). Each frame is solved on its own (the previous frame's answer warm-starts the
  iterative solver) and reports its residual ``||K u - f|| / ||f||`` on the free unknowns.

The truth leaves the program as a displacement field on the planning image's grid (:mod:`warpmpm.fields`):
at each planning voxel the displacement (mm, world LPS axes) of the tissue there. Outside the meshed region
(air, or beyond the box) the field takes its nearest meshed node's value.

Not modelled, and why: hyperelasticity (the frames record the 99th-percentile principal strain in the organs so a
reader sees where linear elasticity is stretched; 3-8 % on the samples at 8-20 mm breathing), gravity and
pressure (the loads are kinematic), frictionless contact (see sliding above).
"""

from ..anatomy import ANCHOR_LABELS, LIVER_LABELS, TISSUE_RANGES, TISSUES, TissueRange, body_mask, tissue_map
from .config import DIRECT_MAX_DOFS, LOADS, TruthConfig
from .elements import CORNERS, ElasticSolver, assemble, reference_matrices
from .loads import (BreathingCycles, anatomical_axes, cell_eigenstrain, diaphragm_displacement, draw_loads,
                    load_state)
from .mesh import BoxMesh, build_abdomen_mesh, draw_materials
from .series import AbdomenModel, TruthSeries, make_truth, write_truth

__all__ = ["LOADS", "DIRECT_MAX_DOFS", "TruthConfig", "CORNERS", "reference_matrices", "assemble", "ElasticSolver",
           "BoxMesh", "draw_materials", "build_abdomen_mesh", "anatomical_axes", "BreathingCycles", "draw_loads",
           "cell_eigenstrain", "load_state", "diaphragm_displacement", "TruthSeries", "AbdomenModel", "make_truth",
           "write_truth", "ANCHOR_LABELS", "LIVER_LABELS", "TISSUE_RANGES", "TISSUES", "TissueRange", "body_mask",
           "tissue_map"]
