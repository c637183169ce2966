"""legslam: language-enhanced Gaussian-splatting RGB-D SLAM on the CPU."""

from .render import Render, render

__version__ = "0.1.0"
__all__ = ["render", "Render", "__version__"]
