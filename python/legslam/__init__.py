"""legslam: language-enhanced Gaussian-splatting RGB-D SLAM on the CPU. `datasets` reads RGB-D
sequences, `slam` runs the loop (`pipeline` a sequence into a run folder), `features` and
`query` do the language side, `eval` every metric, `cli` the `legslam` command; `render`,
`map` and `tracking` are the engine's rasterizer, Gaussian map and tracker."""

from .render import Render, render

__version__ = "0.1.0"
__all__ = ["render", "Render", "__version__"]
