"""How crowded a frame's particle images are: the share of each view they cover.

The perspective-shift locator tells particles apart by their images. Two particles whose
images merge in most views give one region per view and are easily taken for one, so its
recall is set by how much of the views the images cover, not by the number of particles
per microlens. The measure is the source density ``N_s``: the summed area of the
particle images in the central view over the view's area. Large particles, or a high
magnification, crowd the images at few particles per microlens.

On the acceptance envelope of ``benchmarks/accuracy_matrix.py`` (realistic optics,
validation seeds; 2026-12-02), recall by source density:

==============  ===============================================  ======
``N_s``         cell                                             recall
==============  ===============================================  ======
0.012-0.08      0.2, 0.4, 0.5 mm; magnification -0.3 and -0.75   0.99-1
0.137           magnification -1                                 0.92
0.151           2 mm particles                                   0.94
0.191           0.025 particles per microlens                    0.96
0.209           1 mm particles                                   0.87
0.376           0.05 particles per microlens                     0.55
0.760           0.1 particles per microlens                      0.23
==============  ===============================================  ======

:func:`source_density` computes ``N_s`` for a planned (or simulated) field of particles;
:func:`image_coverage` measures the coverage of a located frame from its segmented regions
(their summed area over the view's pixels, the median over the views). The two agree
while images seldom merge: on simulated `small` frames (realistic optics) the coverage
read 0.053 for a true ``N_s`` of 0.037, 0.13-0.16 for 0.135-0.139, 0.22-0.25 for 0.21 and
0.40 for 0.37 (ideal optics: 0.067 for 0.046, 0.23 for 0.19, 0.37 for 0.38); it saturates
above (0.65 for 0.75 and 0.50 for 0.72), where merged images cover less than the sum of
their areas. Sparse frames read a little high: a thresholded region is larger than the
image by part of its blurred edge. :func:`~plenoptrack.locate.perspective.locate_frame` reports the
coverage and warns (:class:`~plenoptrack.errors.CrowdedFrameWarning`) above
:data:`CROWDED_COVERAGE`.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

__all__ = ["CROWDED_COVERAGE", "image_coverage", "source_density"]

CROWDED_COVERAGE = 0.15
"""Coverage above which a frame is crowded. Up to a source density of 0.08 the locator
found at least 99 % of the particles on every sparse cell of its acceptance envelope;
from 0.14 on it missed 4-13 % (module notes). The coverage of a sparse frame reads about
0.02 above its source density, and the test and example frames of this package, which
the locator handles, read 0.11-0.14: a bar at 0.1 warned on frames that lose a particle
or two at most."""

_MIN_VALID_FRACTION = 0.5
"""Views with less than this share of valid samples (the aperture's rim) are not counted
in the median of :func:`image_coverage`."""


def image_coverage(detections: pd.DataFrame, lf) -> float:
    """Share of each view that the frame's particle images cover: the median over the
    views of the summed area of their regions over the view's pixels.

    Parameters
    ----------
    detections : DataFrame
        The frame's regions (:func:`~plenoptrack.locate.segment.segment_views`): at least
        the columns ``u, v`` (view) and ``area`` (view pixels).
    lf : LightField
        The decoded frame: its ``spatial_mask`` (pixels of a view), view coordinates
        ``u, v`` and ``valid_fraction`` (share of valid samples of each view; views below
        one half are not counted).

    Returns
    -------
    float
        The coverage, 0 to about 1; 0 for a frame without regions. It follows the source
        density ``N_s`` up to about 0.4 (module notes).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> lf = SimpleNamespace(spatial_mask=np.ones((10, 10), bool), u=np.array([-1.0, 0, 1]),
    ...                      v=np.array([0.0]), valid_fraction=np.ones((1, 3)))
    >>> det = pd.DataFrame({"u": [0.0, 0.0, 1.0], "v": [0.0, 0.0, 0.0], "area": [6, 4, 30]})
    >>> image_coverage(det, lf)   # views cover nothing, 0.1 and 0.3
    0.1
    """
    pixels = int(np.count_nonzero(lf.spatial_mask))
    vv, uu = np.nonzero(np.asarray(lf.valid_fraction) >= _MIN_VALID_FRACTION)
    if len(vv) == 0 or pixels == 0:
        return 0.0
    counted = pd.MultiIndex.from_arrays([np.asarray(lf.u, float)[uu], np.asarray(lf.v, float)[vv]],
                                        names=["u", "v"])
    area = (detections.groupby(["u", "v"])["area"].sum() if len(detections)
            else pd.Series(dtype=float))
    # views without a region cover nothing
    per_view = area.reindex(counted, fill_value=0.0).to_numpy(float) / pixels
    return float(np.median(per_view))


def source_density(truth: pd.DataFrame, camera) -> float:
    """Source density ``N_s`` of a field of particles: the summed area of their images in
    the central view over the view's area.

    Parameters
    ----------
    truth : DataFrame
        One row per particle: depth ``z`` (mm, positive away from the camera) and
        ``diameter`` (mm).
    camera : CameraSpec
        The camera (object distance, magnification, aperture, microlens grid).

    Returns
    -------
    float
        ``N_s``. Each image is the particle's geometric image plus the blur of the
        central view's sub-aperture at its depth: ``|M| (d s_o / (s_o + z) + a |z| /
        (s_o + z))`` on the microlens plane (``s_o`` object distance, ``a`` the aperture
        diameter over the pixels per lenslet), over the microlens array's area.

    Examples
    --------
    >>> from plenoptrack import preset
    >>> camera = preset("small")
    >>> field = pd.DataFrame({"z": [0.0] * 20, "diameter": [0.4] * 20})
    >>> round(source_density(field, camera), 4)
    0.0384
    """
    s_o = camera.object_distance_mm
    m = abs(camera.magnification)
    z = truth["z"].to_numpy(float)
    d = truth["diameter"].to_numpy(float)
    sub_aperture = camera.aperture_diameter_mm / camera.pixels_per_lenslet
    image = m * (d * s_o / (s_o + z) + sub_aperture * np.abs(z) / (s_o + z))   # mm on the MLA
    rows, cols = camera.grid_shape
    area = rows * camera.row_pitch_um * 1e-3 * cols * camera.microlens_pitch_um * 1e-3
    return float((math.pi / 4 * image ** 2).sum() / area)
