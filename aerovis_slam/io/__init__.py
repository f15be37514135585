"""Reading and writing event-camera recordings.

* :mod:`aerovis_slam.io.sequence`: the canonical HDF5 sequence (the project's contract).
* :mod:`aerovis_slam.io.source`: the :class:`~aerovis_slam.io.source.Recording` interface every
  reader implements, :func:`~aerovis_slam.io.source.open_recording` (format detection) and
  :func:`~aerovis_slam.io.source.convert` (any recording to the canonical format).
"""
