"""Physically based plenoptic camera simulator with ground truth.

Renders what a back-lit particle experiment with a plenoptic camera records: raw frames,
a white (flat-field) image and dot-card calibration images, by back-tracing rays through
a thin main lens with radial distortion, a perturbed microlens array and a noisy sensor
(:mod:`.optics`, :mod:`.render`, :mod:`.sensor`, :mod:`.dotcard`, :mod:`.psf`,
:mod:`.illumination`, switched by :mod:`.realism`); builds ground-truth
scenes (:mod:`.scene`) of spheres, spheroids or irregular fragments (:mod:`.fragments`)
and writes whole data sets (:mod:`.dataset`). Nothing on the
locating path imports this package.

Examples
--------
>>> from plenoptrack import preset
>>> from plenoptrack.simulate import make_optics, random_particles, default_volume, render_frame
>>> camera = preset("small")
>>> optics = make_optics(camera, seed=0)
>>> particles = random_particles(5, volume=default_volume(camera), diameter_mm=0.5, seed=0)
>>> render_frame(optics, particles, seed=0).shape
(600, 910)
"""

from .dataset import SimulationResult, simulate_dataset
from .dotcard import (CardPlacement, DotCard, default_dotcard, default_dotcard_depths, dot_grid,
                      dotcard_irradiance, draw_card_placements, origin_dot_mm, render_dotcard,
                      sensor_centre_aim_mm)
from .optics import SimOptics, make_optics, true_camera
from .fragments import Fragment, fragment_geometry, fragment_silhouette
from .realism import (BlurEffects, IlluminationEffects, LensEffects, ParticleEffects, Realism,
                      SensorEffects, SpecEffects, TargetEffects, realism_from_dict)
from .render import (expose_image, render_dark, render_frame, render_irradiance, render_repeats,
                     render_white)
from .scene import (Scene, SceneError, Volume, default_diameter_mm, default_volume, load_scene,
                    make_scene, moving_particles, particle_silhouettes,
                    random_particles, with_particle_effects)
from .sensor import SensorModel

__all__ = [
    "SimOptics", "make_optics", "true_camera",
    "Realism", "BlurEffects", "LensEffects", "IlluminationEffects", "SensorEffects", "TargetEffects",
    "SpecEffects", "ParticleEffects", "realism_from_dict", "CardPlacement",
    "draw_card_placements", "origin_dot_mm", "sensor_centre_aim_mm",
    "render_white", "render_frame", "render_repeats", "render_irradiance", "render_dark", "expose_image",
    "DotCard", "default_dotcard", "default_dotcard_depths", "dot_grid", "render_dotcard",
    "dotcard_irradiance",
    "Scene", "SceneError", "Volume", "default_volume", "default_diameter_mm", "random_particles",
    "moving_particles", "particle_silhouettes", "with_particle_effects",
    "Fragment", "fragment_geometry", "fragment_silhouette",
    "make_scene", "load_scene",
    "SensorModel", "simulate_dataset", "SimulationResult",
]
