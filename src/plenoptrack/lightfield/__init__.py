"""Light-field decoding: lenslet grid, 4D light field, perspective views, refocusing."""

from .lattice import LensletGrid

__all__ = ["LensletGrid"]
