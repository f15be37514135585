"""Stereo event-inertial SLAM runtime (AERO-VIS / OKVIS2 design; numpy, OpenCV, ONNX Runtime, gtsam).

Where things live:

* :mod:`~aerovis_slam.slam.config`: :class:`SlamConfig` and ``conf/slam/*.yaml`` loading.
* :mod:`~aerovis_slam.slam.preprocessing`: events with IMU coverage into per-camera timestamp buffers, MCTS.
* :mod:`~aerovis_slam.slam.detectors`: the classical stereo detector wrapper (learned ones: :mod:`aerovis_slam.bundle`).
* :mod:`~aerovis_slam.slam.stereo`, :mod:`~aerovis_slam.slam.ransac`: epipolar matching, triangulation,
  3D-2D and rotation-only 2D-2D RANSAC.
* :mod:`~aerovis_slam.slam.imu`: IMU preintegration (gtsam) and visual-inertial initialisation.
* :mod:`~aerovis_slam.slam.cameras`: the stereo camera model at the MCTS resolution (frames, crops).
* :mod:`~aerovis_slam.slam.frontend`: landmark map, matching, keyframe decision.
* :mod:`~aerovis_slam.slam.backend`: the gtsam fixed-lag keyframe smoother and per-frame tracking.
* :mod:`~aerovis_slam.slam.odometry`: one frontend + backend iteration per frame, initialisation,
  failure handling, loop-closure corrections.
* :mod:`~aerovis_slam.slam.pipeline`: :func:`run_slam` with the ``sync``/``async``/``live`` modes.
* :mod:`~aerovis_slam.slam.trajectory`, :mod:`~aerovis_slam.slam.loop`, :mod:`~aerovis_slam.slam.report`,
  :mod:`~aerovis_slam.slam.cli`, :mod:`~aerovis_slam.slam.bench`: TUM files and ATE/RPE, loop closure,
  reports, the ``aerovis-slam`` command and its benchmark.

Nothing is imported here, so that ``import aerovis_slam.slam.<module>`` stays cheap.
"""
