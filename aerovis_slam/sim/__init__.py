"""Event-camera simulator: textured rooms, smooth trajectories, IMU, ESIM events, frames, depth.

* :mod:`~aerovis_slam.sim.scene`: procedural rooms of textured planes, exact rendering and depth.
* :mod:`~aerovis_slam.sim.trajectory`: smooth trajectories with analytic derivatives.
* :mod:`~aerovis_slam.sim.imu`: gyroscope and accelerometer with Kalibr-style noise.
* :mod:`~aerovis_slam.sim.events`: the ESIM event generator with v2e-style noise; video to events.
* :mod:`~aerovis_slam.sim.rig`: rig YAML files (``conf/rig``) as :class:`~aerovis_slam.calib.RigCalibration`.
* :mod:`~aerovis_slam.sim.simulator`: the loop, in memory (:func:`simulate`) or to a canonical file
  (:func:`write_sequence`).
* :mod:`~aerovis_slam.sim.presets`, :mod:`~aerovis_slam.sim.cli` (``aerovis-sim``),
  :mod:`~aerovis_slam.sim.cache` (:func:`ensure_preset`), :mod:`~aerovis_slam.sim.bench`.
"""

from .cache import ensure_preset
from .events import EventConfig, EventGenerator, video_to_events
from .presets import PRESETS, preset_specs
from .rig import load_rig, scale_rig
from .scene import Scene, make_scene
from .simulator import SequenceSpec, SimResult, Simulator, simulate, tone_map, write_sequence
from .trajectory import TRAJECTORY_KINDS, Trajectory, make_trajectory

__all__ = [
    "EventConfig", "EventGenerator", "PRESETS", "Scene", "SequenceSpec", "SimResult", "Simulator", "TRAJECTORY_KINDS",
    "Trajectory", "ensure_preset", "load_rig", "make_scene", "make_trajectory", "preset_specs", "scale_rig", "simulate",
    "tone_map", "video_to_events", "write_sequence",
]
