"""Particle location from decoded light fields (the perspective-shift method).

The usual entry point is :func:`locate_frame` with its settings
:class:`PerspectiveLocator` (read from a TOML file by :func:`read_settings`); the steps it composes are public too:
:func:`segment_views` (per-view segmentation), :func:`cluster_detections`
(projected-plane k-means), :func:`fit_dlfc` / :class:`DLFC` (volumetric calibration) and
:func:`triangulate_clusters` (3D solve with outlier rejection).
"""

from .cluster import Clustering, ProjectionGeometry, cluster_detections, plane_alphas
from .dlfc import DLFC, FitReport, fit_dlfc
from .dotcards import (CardLattice, OriginConsensus, card_lattice, consistent_origins,
                       dotcard_points, index_dotcard, index_lattice)
from .crowding import CROWDED_COVERAGE, image_coverage, source_density
from .perspective import PARTICLE_COLUMNS, LocateResult, locate_frame
from .settings import (CheckSettings, ClusterSettings, GrowSettings, PerspectiveLocator,
                       SegmentSettings, SolveSettings, read_settings, settings_toml)
from .segment import DETECTION_COLUMNS, segment_array, segment_view, segment_views
from .triangulate import (Triangulation, TriangulationFlag, predict_detection,
                          triangulate_cluster, triangulate_clusters)

__all__ = [
    "locate_frame", "PerspectiveLocator", "LocateResult", "PARTICLE_COLUMNS",
    "SegmentSettings", "ClusterSettings", "SolveSettings", "GrowSettings", "CheckSettings",
    "read_settings", "settings_toml",
    "segment_views", "segment_view", "segment_array", "DETECTION_COLUMNS",
    "cluster_detections", "Clustering", "ProjectionGeometry", "plane_alphas",
    "DLFC", "FitReport", "fit_dlfc", "dotcard_points", "index_dotcard", "index_lattice",
    "card_lattice", "CardLattice", "consistent_origins", "OriginConsensus",
    "triangulate_clusters", "triangulate_cluster", "Triangulation", "TriangulationFlag",
    "predict_detection", "image_coverage", "source_density", "CROWDED_COVERAGE",
]
