"""Export of trained keypoint networks to deployable model bundles (ONNX FP32/FP16/INT8, TensorRT).

A bundle is a directory with ``model.onnx``, ``metadata.json`` and ``parity.json``; the SLAM
runtime loads it with :class:`aerovis_slam.bundle.Bundle` (no torch needed there).
"""
