"""Physically based plenoptic camera simulator with ground truth.

Renders what a back-lit particle experiment with a plenoptic camera records: raw frames,
a white (flat-field) image and dot-card calibration images, by back-tracing rays through
a thin main lens with radial distortion, a perturbed microlens array and a noisy sensor.
Nothing on the locating path imports this package.
"""

from .optics import SimOptics, make_optics
from .render import render_frame, render_irradiance, render_white
from .sensor import SensorModel

__all__ = ["SimOptics", "make_optics", "render_white", "render_frame", "render_irradiance",
           "SensorModel"]
