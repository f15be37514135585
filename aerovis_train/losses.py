"""Training losses of the keypoint networks (SuperPoint heritage).

* Detector: 65-class cross-entropy per 8x8 cell (64 positions + dustbin).
* Descriptor: hinge loss on the dense grid, positives pulled above ``pos_margin`` (1) and negatives
  pushed below ``neg_margin`` (0.2) in cosine similarity. The positive and negative terms are each
  averaged over their own pairs and mixed by ``pos_weight`` (0.5): about one cell pair in a thousand
  is positive, and separate means keep the balance independent of the image size (SuperPoint's
  lambda_d = 250 does the same job for one fixed size).
* Or (``loss.descriptor: dual_softmax``, depth supervision only): a cross-entropy of each visible
  cell's true match among all cells of the other view, in both directions (the row and column
  softmax of LoFTR's coarse matching). It scores the nearest-neighbour decision that mutual-nearest-
  neighbour matching makes, where the hinge scores each cell pair against fixed margins.
* Or (``loss.descriptor: hinge+dual_softmax``, depth only): both, hinge + ``dual_softmax_weight`` (0.1)
  * dual softmax. The softmax ranks the true match first; the hinge keeps similarities calibrated
  (true matches near 1, others below 0.2), which a fixed similarity threshold, as in the SLAM
  runtime's tracking, relies on.
* Optionally (``loss.repeatability`` > 0, depth only): R2D2's repeatability loss on the keypoint
  probability maps. Each view's map, warped into the other by depth and pose, must have the same
  local shape: 1 - the cosine similarity of the two maps over overlapping patches. The corner labels
  teach where corners of the intensity frame are; this term teaches the network to fire at the same
  scene points in both views wherever it fires, which is what the evaluation's top-k keypoints need.
* Total = det0 + det1 + ``desc_weight`` (10) * desc (+ ``repeatability`` * rep).

Targets come from :mod:`aerovis_train.correspondences`: with depth, cell centres warped into the
other view; with poses alone, epipolar lines (multiple-instance positive: the most similar cell near
the line must match, cells far from it are negatives).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .correspondences import cell_centres

#: the descriptor losses ``loss.descriptor`` names
DESCRIPTOR_LOSSES = ("hinge", "dual_softmax", "hinge+dual_softmax")


def descriptor_loss_terms(kind: str, supervision: str) -> list[str]:
    """The terms of ``loss.descriptor`` (``"hinge+dual_softmax"`` -> ``["hinge", "dual_softmax"]``), checked.

    Args:
        kind: the ``loss.descriptor`` setting.
        supervision: ``"depth"`` (one true cell per cell) or ``"epipolar"`` (poses only: a line of candidates).

    Raises:
        ValueError: an unknown setting, or the dual softmax without depth (its cross-entropy needs the one
            true cell that only depth supervision gives).
    """
    if kind not in DESCRIPTOR_LOSSES:
        raise ValueError(f"loss.descriptor={kind!r}: expected one of {', '.join(DESCRIPTOR_LOSSES)}")
    terms = kind.split("+")
    if "dual_softmax" in terms and supervision != "depth":
        raise ValueError(f"loss.descriptor={kind} needs data.supervision=depth (this data has {supervision!r}: poses "
                         "only give epipolar lines, not one true cell); use loss.descriptor=hinge")
    return terms


def detector_loss(logits: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of (B, 65, Hc, Wc) logits against (B, Hc, Wc) int64 labels (-100 = ignore), or
    against (B, 65, Hc, Wc) float target distributions (sub-pixel labels, :func:`~aerovis_train.labels.soft_cell_labels`)."""
    if labels.is_floating_point():
        return F.cross_entropy(logits, labels)
    return F.cross_entropy(logits, labels, ignore_index=-100)


def _cell_centres(hc: int, wc: int, cell: int, device) -> torch.Tensor:
    """(hc*wc, 2) float32 cell centres, the same convention as the targets (one implementation)."""
    return torch.from_numpy(cell_centres(hc * cell, wc * cell, cell)).float().to(device)


def _warp_distances(desc1: torch.Tensor, warped01: torch.Tensor, cell: int) -> torch.Tensor:
    """(B, N0, N1) px from where each view-0 cell centre lands in view 1 (``warped01``, NaN: invisible,
    then far from everything) to every view-1 cell centre of the (B, D, Hc, Wc) grid ``desc1``."""
    B, _, hc, wc = desc1.shape
    centres = _cell_centres(hc, wc, cell, desc1.device)
    return torch.cdist(torch.nan_to_num(warped01, nan=1e9), centres.unsqueeze(0).expand(B, -1, -1))


def _hinge(sim, pos, neg, pos_margin, neg_margin, pos_weight):
    zero = sim.new_zeros(())
    lp = F.relu(pos_margin - sim)[pos].mean() if bool(pos.any()) else zero
    ln = F.relu(sim - neg_margin)[neg].mean() if bool(neg.any()) else zero
    return pos_weight * lp + (1 - pos_weight) * ln


def descriptor_loss_depth(
    desc0: torch.Tensor,
    desc1: torch.Tensor,
    warped01: torch.Tensor,
    *,
    cell: int = 8,
    pos_px: float = 6.0,
    neg_px: float = 12.0,
    pos_margin: float = 1.0,
    neg_margin: float = 0.2,
    pos_weight: float = 0.5,
) -> torch.Tensor:
    """Dense hinge loss with depth-warped cell centres.

    Args:
        desc0, desc1: (B, D, Hc, Wc) L2-normalised descriptor grids.
        warped01: (B, Hc*Wc, 2) where each view-0 cell centre lands in view 1 (NaN: invisible).
        pos_px: cells of view 1 whose centre is within this of the warped point are positives (6 px:
            the nearest cell centre is at most 4*sqrt(2) = 5.7 px away, so a visible point always has one).
        neg_px: beyond this, negatives; in between ignored. Invisible cells are negatives to all.
    """
    dist = _warp_distances(desc1, warped01, cell)
    pos = dist <= pos_px
    neg = dist > neg_px
    sim = torch.einsum("bdn,bdm->bnm", desc0.flatten(2), desc1.flatten(2))
    return _hinge(sim, pos, neg, pos_margin, neg_margin, pos_weight)


def descriptor_loss_epipolar(
    desc0: torch.Tensor,
    desc1: torch.Tensor,
    lines01: torch.Tensor,
    *,
    cell: int = 8,
    pos_px: float = 4.0,
    neg_px: float = 12.0,
    pos_margin: float = 1.0,
    neg_margin: float = 0.2,
    pos_weight: float = 0.5,
) -> torch.Tensor:
    """Pose-only hinge loss: cells far (> neg_px) from a cell's epipolar line are negatives; the most
    similar cell within ``pos_px`` of the line is pulled towards it (the true match lies on the line).

    Args:
        lines01: (B, Hc*Wc, 3) normalised epipolar lines in view 1 of view-0 cell centres.
    """
    B, D, hc, wc = desc1.shape
    centres = _cell_centres(hc, wc, cell, desc0.device)
    h = torch.cat([centres, torch.ones_like(centres[:, :1])], 1)  # (N1, 3)
    dist = torch.einsum("bnk,mk->bnm", lines01, h).abs()
    sim = torch.einsum("bdn,bdm->bnm", desc0.flatten(2), desc1.flatten(2))
    near = dist <= pos_px
    neg = dist > neg_px
    best = sim.masked_fill(~near, -2.0).amax(2)  # (B, N0), -2 where no cell is near the line
    has = near.any(2)
    zero = sim.new_zeros(())
    lp = F.relu(pos_margin - best[has]).mean() if bool(has.any()) else zero
    ln = F.relu(sim - neg_margin)[neg].mean() if bool(neg.any()) else zero
    return pos_weight * lp + (1 - pos_weight) * ln


def descriptor_loss_dual_softmax(
    desc0: torch.Tensor,
    desc1: torch.Tensor,
    warped01: torch.Tensor,
    *,
    cell: int = 8,
    pos_px: float = 6.0,
    neg_px: float = 12.0,
    temperature: float = 0.1,
) -> torch.Tensor:
    """Dense matching cross-entropy with depth-warped cell centres (written here: the losses of the
    matching libraries at hand (kornia's LoFTR, LightGlue) come inside their models, not on a grid of
    our targets).

    Each view-0 cell whose warped centre has a view-1 cell centre within ``pos_px`` takes the nearest one
    as its match; its similarities to every view-1 cell, divided by ``temperature``, are a softmax over
    which the match's negative log-likelihood is taken, and the same for the match's column over the
    view-0 cells. Other cells within ``neg_px`` of the match's position (neighbours of the true cell,
    whose descriptors may rightly be alike) are left out of both softmaxes.

    Args:
        desc0, desc1: (B, D, Hc, Wc) L2-normalised descriptor grids.
        warped01: (B, Hc*Wc, 2) where each view-0 cell centre lands in view 1 (NaN: invisible).
        temperature: scale of the cosine similarities in the softmax (0.1: logits in [-10, 10]).
    Returns:
        Mean of the row and column cross-entropies over the matched cells; 0 when no cell has a match.
    """
    dist = _warp_distances(desc1, warped01, cell)
    nearest_px, target = dist.min(2)  # (B, N0)
    has = nearest_px <= pos_px
    if not bool(has.any()):
        return desc0.new_zeros(())
    is_target = torch.zeros_like(dist, dtype=torch.bool).scatter_(2, target.unsqueeze(2), True) & has.unsqueeze(2)
    ignore = (dist <= neg_px) & ~is_target
    sim = torch.einsum("bdn,bdm->bnm", desc0.flatten(2), desc1.flatten(2)) / temperature
    sim = sim.masked_fill(ignore, float("-inf"))
    row = -torch.log_softmax(sim, dim=2)[is_target]  # each matched view-0 cell among the view-1 cells
    col = -torch.log_softmax(sim, dim=1)[is_target]  # its match among the view-0 cells
    return 0.5 * (row.mean() + col.mean())


def repeatability_weight(loss_cfg) -> float:
    """``loss.repeatability`` as a number (0 when unset: the loss is off)."""
    return float(loss_cfg.get("repeatability", 0.0) or 0.0)


def repeatability_loss(scores0: torch.Tensor, scores1: torch.Tensor, flow01: torch.Tensor, *, patch: int = 8,
                       min_visible: float = 0.5) -> torch.Tensor:
    """R2D2's repeatability loss (Revaud et al. 2019), written here (kornia has no loss of this kind).

    ``scores1`` is sampled bilinearly where each pixel of view 0 lands (``flow01``), so both maps are in
    view 0's pixels. Over patches of ``patch`` x ``patch`` pixels, overlapping by half, the loss is one minus
    the cosine similarity of ``scores0`` and the warped ``scores1``: it is 0 when the two maps have the same
    local shape (peaks at the same scene points, whatever their height) and does not care about the
    maps' overall level, which the 65-class cross-entropy sets.

    Args:
        scores0, scores1: (B, H, W) keypoint probability maps of the two views.
        flow01: (B, H, W, 2) float: where each pixel (x, y) of view 0 lands in view 1, in view-1 pixels
            (NaN: invisible).
        patch: patch side in pixels (8: one cell).
        min_visible: patches with a smaller share of visible pixels are left out.
    Returns:
        Scalar mean of ``1 - cos`` over the kept patches; 0 when none is kept.
    """
    h1, w1 = scores1.shape[-2:]
    visible = torch.isfinite(flow01).all(-1)
    flow = torch.nan_to_num(flow01, nan=-1e4)
    # pixel centres at integer coordinates: align_corners=True maps 0 and w1 - 1 to -1 and +1
    grid = torch.stack([2.0 * flow[..., 0] / max(w1 - 1, 1) - 1.0, 2.0 * flow[..., 1] / max(h1 - 1, 1) - 1.0], dim=-1)
    warped = F.grid_sample(scores1.unsqueeze(1), grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    m = visible.unsqueeze(1).to(scores0.dtype)
    a, b = scores0.unsqueeze(1) * m, warped * m
    stride = max(1, patch // 2)
    pool = lambda x: F.avg_pool2d(x, patch, stride)  # noqa: E731
    ab, aa, bb = pool(a * b), pool(a * a), pool(b * b)
    # clamped inside the root: sqrt's gradient at 0 is infinite, and 0 * inf poisons even left-out patches
    cos = ab / torch.sqrt((aa * bb).clamp_min(1e-24))
    keep = pool(m) >= min_visible
    if not bool(keep.any()):
        return scores0.new_zeros(())
    return (1.0 - cos)[keep].mean()
