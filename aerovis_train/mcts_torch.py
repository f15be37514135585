"""Batched MCTS in torch (GPU-friendly), equal to :mod:`aerovis_slam.mcts` (tests prove it).

Same equations, same polarity-major channel order (``channel = p * K + k``), same float32
arithmetic: ``max(0, 1 - float32(tau - t) * float32(1 / dt_k))``.

The latest-timestamp buffer is built with ``scatter_reduce(amax)``: events are time-sorted, so
the maximum is the newest, and a reduction is deterministic where a plain scatter of duplicate
indices would race on a GPU.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from aerovis_slam.mcts import MCTS_DT_WINDOWS_MS, MCTS_NE_EVENTS_PER_PX, NO_EVENT, events_per_window


def timestamp_buffer(t, x, y, p, batch: torch.Tensor | None, batch_size: int, width: int, height: int) -> torch.Tensor:
    """Newest timestamp per sample, polarity and pixel.

    Args:
        t: (N,) int64 µs. x, y: (N,) pixel coordinates. p: (N,) polarity 0/1.
        batch: (N,) sample index of each event (None: all in sample 0).
        batch_size: B.
    Returns:
        (B, 2, H, W) int64, :data:`~aerovis_slam.mcts.NO_EVENT` where a pixel has no event.
    """
    device = t.device
    if batch is None:
        batch = torch.zeros_like(t)
    idx = ((batch.long() * 2 + p.long()) * height + y.long()) * width + x.long()
    ts = torch.full((batch_size * 2 * height * width,), int(NO_EVENT), dtype=torch.int64, device=device)
    ts.scatter_reduce_(0, idx, t.long(), reduce="amax", include_self=True)
    return ts.view(batch_size, 2, height, width)


def surfaces(ts: torch.Tensor, tau: torch.Tensor, windows_us: torch.Tensor) -> torch.Tensor:
    """Time surfaces from buffers.

    Args:
        ts: (B, 2, H, W) int64 buffers.
        tau: (B,) int64 surface times (µs).
        windows_us: (B, K) float64 windows (µs).
    Returns:
        (B, 2K, H, W) float32, polarity-major.
    """
    B, _, H, W = ts.shape
    K = windows_us.shape[1]
    age = (tau.view(B, 1, 1, 1) - ts).to(torch.float32)
    inv_dt = (1.0 / windows_us.to(torch.float64)).to(torch.float32)
    v = 1.0 - age.unsqueeze(2) * inv_dt.view(B, 1, K, 1, 1)
    return v.clamp_min_(0.0).view(B, 2 * K, H, W)


def _sample_bounds(batch: torch.Tensor | None, n: int, batch_size: int, device):
    if batch is None:
        counts = torch.tensor([n], device=device)
    else:
        counts = torch.bincount(batch.long(), minlength=batch_size)
    ends = torch.cumsum(counts, 0)
    return ends - counts, ends, counts


def mcts_ne(
    t, x, y, p, *, width: int, height: int, batch: torch.Tensor | None = None, batch_size: int = 1,
    tau: torch.Tensor | None = None, events_per_px: Sequence[float] = MCTS_NE_EVENTS_PER_PX,
) -> torch.Tensor:
    """MCTS_Ne of a batch: (B, 2K, H, W) float32.

    Events must be grouped by sample (``batch`` non-decreasing) and time-sorted within each sample.
    ``tau`` (B,) defaults to each sample's newest event and must not precede it.
    """
    starts, ends, counts = _sample_bounds(batch, len(t), batch_size, t.device)
    if bool((counts == 0).any()):
        raise ValueError(f"every sample needs at least one event; empty samples: {torch.nonzero(counts == 0).flatten().tolist()}")
    last_t = t[ends - 1]
    tau = last_t if tau is None else tau.to(t.device).long()
    if bool((tau < last_t).any()):
        raise ValueError("tau precedes the newest event of a sample; pass only events up to tau")
    n_k = torch.as_tensor(events_per_window(events_per_px, width, height), device=t.device)
    ref = torch.maximum((ends - 1).unsqueeze(1) - n_k.unsqueeze(0), starts.unsqueeze(1))  # (B, K)
    windows = (tau.unsqueeze(1) - t[ref]).clamp_min(1).to(torch.float64)
    ts = timestamp_buffer(t, x, y, p, batch, batch_size, width, height)
    return surfaces(ts, tau, windows)


def mcts_dt(
    t, x, y, p, *, width: int, height: int, batch: torch.Tensor | None = None, batch_size: int = 1,
    tau: torch.Tensor | None = None, windows_ms: Sequence[float] = MCTS_DT_WINDOWS_MS,
) -> torch.Tensor:
    """MCTS_dt of a batch: (B, 2K, H, W) float32, fixed windows in ms."""
    starts, ends, counts = _sample_bounds(batch, len(t), batch_size, t.device)
    if tau is None:
        if bool((counts == 0).any()):
            raise ValueError("tau is required for samples without events")
        tau = t[ends - 1]
    tau = tau.to(t.device).long()
    windows = torch.as_tensor([w * 1000.0 for w in windows_ms], dtype=torch.float64, device=t.device).expand(batch_size, -1)
    ts = timestamp_buffer(t, x, y, p, batch, batch_size, width, height)
    return surfaces(ts, tau, windows)
