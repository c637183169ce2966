"""The SLAM loop and its parts: `SLAM` (a short `step` per frame), `SLAMConfig` (every option,
with the engine's mapper and tracker sections), and the components the loop runs: the tracking
policy, the fused surface it tracks against, the keyframe policy, the feature feed, and inline
or threaded mapping; and the keyframe pose graph that loop closure optimises (`PoseGraph`).

    from legslam.slam import SLAM, SLAMConfig
"""

from .config import DERIVED, MapperOptions, SLAMConfig, TrackerOptions
from .pose_graph import PoseGraph
from .system import SLAM, StepResult

__all__ = ["SLAM", "SLAMConfig", "StepResult", "MapperOptions", "TrackerOptions", "DERIVED",
           "PoseGraph"]
