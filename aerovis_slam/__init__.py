"""aerovis_slam: the deployable runtime of aerovis (numpy, OpenCV, ONNX Runtime; never torch).

Event I/O (:mod:`aerovis_slam.io`), the multi-channel time surfaces (:mod:`aerovis_slam.mcts`)
shared with training, and (later) the stereo event-inertial SLAM pipeline.
"""

__version__ = "0.1.0"
