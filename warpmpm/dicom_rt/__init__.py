"""DICOM for the planning system: a planning series, RT Structure Sets in and out, Deformable Spatial Registrations out.

Written with pydicom (the DICOM file layer: tags, value representations, file meta), with the information
objects built here attribute by attribute from DICOM PS3.3 and checked by dicom3tools' ``dciodvfy`` in the
tests. Contours come from contourpy (matplotlib's contouring library) and are rasterised with matplotlib's
point-in-polygon; both already come with this package's dependencies.

Conventions (all positions in mm in the DICOM patient coordinate system, which is world LPS, the same axes as
every other output of this package):

- **Planning series** (:func:`write_series`): one single-frame image per slice of the planning grid along its third
  axis, in the grid's own orientation (ImageOrientationPatient = its first two axes), intensities kept when they
  are integers that fit 16 bits, else rescaled (RescaleSlope / RescaleIntercept for CT; a linear map to 0-4095
  for MR, said in the ImageComments). It exists for the structure sets and registrations to reference.
- **RT Structure Set** (:func:`write_rtstruct`): one ROI per organ, one CLOSED_PLANAR contour per connected
  outline on each slice it crosses (holes as separate contours: read them even-odd), traced at the half-voxel
  boundary so that the voxels whose centres lie inside are the mask.
- **Deformable Spatial Registration** (:func:`write_registration`): the displacement of the estimate on the
  planning grid, *planning to frame*: the vector at planning grid point x is where the tissue at x is in this
  frame, minus x (mm, LPS). In DICOM's words the Registered RCS is the planning scan's and the Source RCS the
  frame's (the same scanner frame of reference, pre- and post-deformation matrices identity): a point P of the
  planning grid corresponds to P + V(P) in the frame, as resampling the frame onto the planning grid needs.

This software is a research tool, not a medical device: its contours and registrations are estimates to be
reviewed, never to plan or deliver a treatment without review.
"""

from .common import STRUCTURE_NAMES, SeriesReference
from .frames import FrameDicomWriter
from .planning import case_from_rtstruct
from .registration import read_registration, write_registration
from .rtdose import write_rtdose
from .rtstruct import find_structures, read_rtstruct, write_rtstruct
from .series import read_series_reference, write_series

__all__ = ["SeriesReference", "STRUCTURE_NAMES", "write_series", "read_series_reference", "write_rtstruct", "read_rtstruct",
           "find_structures", "write_registration", "read_registration", "case_from_rtstruct", "FrameDicomWriter",
           "write_rtdose"]
