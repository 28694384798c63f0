"""fojax: differentiable, vectorised quadrotor simulation with fractional-order control."""

from fojax import fractional
from fojax.fractional import differintegrate

__all__ = ["differintegrate", "fractional"]
__version__ = "0.1.0"
