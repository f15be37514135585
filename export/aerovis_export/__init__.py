"""Export of trained keypoint networks to deployable model bundles (ONNX FP32/FP16/INT8, TensorRT).

A bundle is a directory with ``model.onnx``, ``metadata.json`` and ``parity.json``; the SLAM
runtime loads it with :class:`aerovis_slam.bundle.Bundle` (no torch needed there).

    >>> from aerovis_export import export_bundle                               # doctest: +SKIP
    >>> export_bundle("superlite", "bundles/superlite-fp16", precision="fp16")  # doctest: +SKIP

Modules: :mod:`~aerovis_export.exporter` (``export_bundle``), :mod:`~aerovis_export.onnx_tools`
(torch -> ONNX, FP16), :mod:`~aerovis_export.quantize` (QAT with torchao PT2E, PTQ with ONNX Runtime),
:mod:`~aerovis_export.data` (calibration MCTS, QAT pairs), :mod:`~aerovis_export.parity`,
:mod:`~aerovis_export.tensorrt` (engines), :mod:`~aerovis_export.cli` (``aerovis-export``).
Importing this package is light; torch loads with the first export.
"""

from __future__ import annotations

__all__ = ["export_bundle"]


def export_bundle(*args, **kwargs):
    """See :func:`aerovis_export.exporter.export_bundle` (imported lazily: it pulls in torch)."""
    from .exporter import export_bundle as _export

    return _export(*args, **kwargs)
