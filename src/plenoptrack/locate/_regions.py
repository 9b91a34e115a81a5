"""Region-level steps of the perspective-shift locator: splitting large elongated regions
into the two particle images they are made of, telling one elongated body from images
merged, and measuring each particle's size and shape from its member regions (merged
images with several dark cores are already split by the segmentation,
:func:`~plenoptrack.locate.segment.segment_array`).

Regions are rows of a detections table (:data:`~plenoptrack.locate.segment.DETECTION_COLUMNS`,
view pixels).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd


def _single_image_area(detections: pd.DataFrame) -> float:
    """What one particle's image covers, pixels: the median area of the whole regions.

    Shares of merged images (``whole`` False) are as large as their particle's image
    would be; in a crowd they would raise the reference until merged regions passed for
    single images. Falls back to every region when none is whole.
    """
    area = detections["area"].to_numpy(float)
    whole = (detections["whole"].to_numpy(bool) if "whole" in detections.columns
             else np.ones(len(area), bool))
    return float(np.median(area[whole] if whole.any() else area))


def pair_half_separation(major, minor):
    """Half the distance between the centres of two equal discs whose union has second
    moment axes ``major`` and ``minor`` (view pixels): two discs of radius ``r`` with
    centres ``c +- a e`` have second moments ``r^2 / 4 + a^2`` along ``e`` and ``r^2 / 4``
    across it, so ``a = sqrt(l1 - l2)`` with ``l = (axis / 4)^2``; their radius is
    ``minor / 2``. 0 for a round region."""
    major, minor = np.asarray(major, dtype=float), np.asarray(minor, dtype=float)
    return np.sqrt(np.maximum((major / 4) ** 2 - (minor / 4) ** 2, 0.0))


def _split_pairs(detections: pd.DataFrame, max_area_ratio: float,
                 elongation: float) -> pd.DataFrame:
    """Replace large elongated regions by the two particle images they are made of.

    A region larger than ``max_area_ratio`` times the median area of the whole regions
    (not shares of merged images, which would raise it in a crowd) and more elongated
    than ``elongation`` (major over minor axis) is taken for the merged image of two
    equal particles, whose centres lie :func:`pair_half_separation` to either side along
    its major axis. Each half gets half the area and a round shape of the minor-axis
    diameter.
    """
    if "whole" not in detections.columns:
        detections = detections.assign(whole=True)
    area = detections["area"].to_numpy(float)
    major = detections["major_axis_px"].to_numpy(float)
    minor = detections["minor_axis_px"].to_numpy(float)
    pair = (area > max_area_ratio * _single_image_area(detections)) & (major > elongation * minor)
    if not pair.any():
        return detections.assign(split_pair=False)
    src = detections[pair]
    half = pair_half_separation(major[pair], minor[pair])
    theta = src["orientation"].to_numpy(float)
    ds, dt = half * np.cos(theta), half * np.sin(theta)
    halves = []
    for sign in (-1.0, 1.0):
        h = src.copy()
        h["s"] = src["s"].to_numpy(float) + sign * ds
        h["t"] = src["t"].to_numpy(float) + sign * dt
        h["area"] = np.maximum(np.round(src["area"].to_numpy(float) / 2), 1).astype(
            detections["area"].dtype)
        h["diameter_px"] = np.sqrt(4.0 * h["area"].to_numpy(float) / math.pi)
        h["major_axis_px"] = minor[pair]
        h["eccentricity"] = 0.0
        h["dark_area"] = src["dark_area"].to_numpy(float) / 2
        h["split_pair"] = True
        h["whole"] = False
        halves.append(h)
    out = pd.concat([detections[~pair].assign(split_pair=False), *halves], ignore_index=True)
    return out.sort_values(["v", "u"], kind="stable").reset_index(drop=True)


ELONGATED_ASPECT = 1.5
"""Regions whose median long axis is at least this many times their short one make an
elongated image (:func:`one_elongated_body`)."""

ELONGATED_ALIGNMENT = 0.95
"""Least mean resultant length of the doubled orientations of an elongated particle's
member regions (1: the same in every view) for them to be one body
(:func:`one_elongated_body`). One rigid body turns little from view to view (the study's
pin stems: median 0.998, 10th percentile 0.98); two images merged into one region turn
with the parallax between them (0.76-0.94 for the 5 elongated particles of two frames of
160 particles of 0.4 mm on the `small` camera, seeds 7 and 8)."""


def member_axes(detections: pd.DataFrame, owner: np.ndarray, n: int,
                members: np.ndarray | None = None) -> np.ndarray:
    """(n, 4) per particle: the median major and minor axis (view pixels) of its member
    regions, their axial mean orientation (radians from ``s`` toward ``t``, the mean of
    the doubled angles halved) and the mean resultant length of the doubled angles (1:
    every region points the same way); NaN for a particle without members. The
    thresholded regions' own second moments. ``members`` (M,) bool limits the regions
    counted (default all those ``owner`` assigns)."""
    mine = owner >= 0
    if members is not None:
        mine &= np.asarray(members, dtype=bool)
    theta = 2.0 * detections["orientation"].to_numpy(float)[mine]
    d = pd.DataFrame({"owner": owner[mine],
                      "major": detections["major_axis_px"].to_numpy(float)[mine],
                      "minor": detections["minor_axis_px"].to_numpy(float)[mine],
                      "cos": np.cos(theta), "sin": np.sin(theta)})
    g = d.groupby("owner")
    med, mean = g[["major", "minor"]].median(), g[["cos", "sin"]].mean()
    out = np.full((n, 4), np.nan)
    rows = med.index.to_numpy()
    c, s = mean["cos"].to_numpy(), mean["sin"].to_numpy()
    out[rows, 0], out[rows, 1] = med["major"].to_numpy(), med["minor"].to_numpy()
    out[rows, 2], out[rows, 3] = 0.5 * np.arctan2(s, c), np.hypot(c, s)
    return out


def one_elongated_body(axes: np.ndarray) -> np.ndarray:
    """(n,) bool: the particles whose member regions (``axes`` (n, 4) of
    :func:`member_axes`) are elongated (:data:`ELONGATED_ASPECT`) the same way in every
    view (:data:`ELONGATED_ALIGNMENT`): one body, not images merged, which turn with the
    parallax between them."""
    major, minor, _, alignment = np.asarray(axes, dtype=float).T
    with np.errstate(invalid="ignore"):
        return ((minor > 0) & (major >= ELONGATED_ASPECT * minor)
                & (alignment >= ELONGATED_ALIGNMENT))


def _region_shape(detections: pd.DataFrame, owner: np.ndarray, n: int) -> pd.DataFrame:
    """In-plane size and shape per particle from its member regions, view pixels.

    The diameter is the median over members of the equivalent diameter of the region's
    shadow, ``sqrt(4 dark_area / pi)`` (summed relative darkness: an opaque object's
    area, nearly independent of defocus blur and of the threshold); the axes are the
    members' second-moment axes scaled by the same shadow-to-threshold ratio; the
    orientation is the axial mean of the members'; ``peak`` is the median of the members'
    peak relative darkness. Whole regions are preferred over the cores and halves that
    merged images were split into, which under-size a particle.
    """
    empty = pd.DataFrame({"diameter_px": np.full(n, np.nan), "major_px": np.full(n, np.nan),
                          "minor_px": np.full(n, np.nan), "orientation": np.full(n, np.nan),
                          "peak": np.full(n, np.nan)})
    mask = owner >= 0
    if not mask.any():
        return empty
    d = detections.loc[mask, ["diameter_px", "major_axis_px", "minor_axis_px", "orientation",
                              "dark_area", "darkness"]].copy()
    d["owner"] = owner[mask]
    d["whole"] = (detections.loc[mask, "whole"].to_numpy(bool) if "whole" in detections.columns
                  else True)
    shadow = np.sqrt(4.0 * np.maximum(d["dark_area"].to_numpy(float), 0.0) / math.pi)
    ratio = shadow / np.maximum(d["diameter_px"].to_numpy(float), 1e-9)
    d["diameter_px"] = shadow
    d["major_axis_px"] *= ratio
    d["minor_axis_px"] *= ratio
    # Orientation is axial (theta ~ theta + pi): average the doubled angle.
    d["c2"] = np.cos(2 * d["orientation"])
    d["s2"] = np.sin(2 * d["orientation"])
    has_whole = d.groupby("owner")["whole"].transform("any").to_numpy(bool)
    g = d[d["whole"].to_numpy(bool) | ~has_whole].groupby("owner")
    med = g[["diameter_px", "major_axis_px", "minor_axis_px", "darkness"]].median()
    out = empty.copy()
    idx = med.index.to_numpy()
    out.loc[idx, "diameter_px"] = med["diameter_px"].to_numpy()
    out.loc[idx, "major_px"] = med["major_axis_px"].to_numpy()
    out.loc[idx, "minor_px"] = med["minor_axis_px"].to_numpy()
    out.loc[idx, "orientation"] = 0.5 * np.arctan2(g["s2"].mean(), g["c2"].mean()).to_numpy()
    out.loc[idx, "peak"] = med["darkness"].to_numpy()
    return out
