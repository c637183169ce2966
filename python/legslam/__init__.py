"""legslam: language-enhanced Gaussian-splatting RGB-D SLAM on the CPU."""

__version__ = "0.1.0"
