"""The Lightning module: keypoint network, pose-supervised losses, relative-pose AUC validation."""

from __future__ import annotations

import lightning as L
from lightning.pytorch.utilities import rank_zero_warn
import torch

from .eval.learned import TorchDetector
from .homographic import merge_batches, warp_views
from .losses import (descriptor_loss_depth, descriptor_loss_dual_softmax, descriptor_loss_epipolar, descriptor_loss_terms, detector_loss,
                     repeatability_loss, repeatability_weight)
from .models import build_model


class KeypointModule(L.LightningModule):
    """Trains a :class:`~aerovis_train.models.keypoint_net.KeypointNet`.

    Args:
        cfg: the resolved run config as a plain dict (``model``, ``loss``, ``optim``, ``val``); saved in
            every checkpoint so a checkpoint alone rebuilds the model.
    """

    def __init__(self, cfg: dict):
        super().__init__()
        self.save_hyperparameters({"cfg": cfg})
        self.cfg = cfg
        self.model = build_model(cfg["model"])
        self.skipped_nonfinite = 0
        self._val_pairs: list[dict] = []
        self._val_unusable: set[tuple[str, str]] = set()
        self._warned_few_pairs = False

    def forward(self, x):
        return self.model(x)

    # -- training ---------------------------------------------------------------------------
    def _losses(self, batch) -> dict[str, torch.Tensor]:
        lc = self.cfg["loss"]
        b = batch["mcts0"].shape[0]
        out = self.model(torch.cat([batch["mcts0"], batch["mcts1"]]))
        logits0, logits1 = out["logits"][:b], out["logits"][b:]
        desc0, desc1 = out["descriptors"][:b], out["descriptors"][b:]
        # a batch with depth targets carries warps; one supervised by poses only carries epipolar lines
        terms = descriptor_loss_terms(lc.get("descriptor", "hinge"), "depth" if "warp01" in batch else "epipolar")
        hinge = dict(pos_margin=lc["pos_margin"], neg_margin=lc["neg_margin"], pos_weight=lc["pos_weight"])
        if "warp01" in batch:
            targets = batch["warp01"], batch["warp10"]
            fns = {"hinge": (descriptor_loss_depth, dict(hinge, pos_px=lc["pos_px"], neg_px=lc["neg_px"])),
                   "dual_softmax": (descriptor_loss_dual_softmax,
                                    dict(pos_px=lc["pos_px"], neg_px=lc["neg_px"], temperature=lc["temperature"]))}
        else:
            targets = batch["lines01"], batch["lines10"]
            fns = {"hinge": (descriptor_loss_epipolar, dict(hinge, pos_px=lc["epipolar_pos_px"], neg_px=lc["neg_px"]))}
        # the combination's softmax term is scaled by loss.dual_softmax_weight relative to the hinge
        weights = {"hinge": 1.0, "dual_softmax": float(lc["dual_softmax_weight"]) if len(terms) > 1 else 1.0}
        desc = 0.0
        for term in terms:
            loss_fn, kw = fns[term]
            # both directions: view 0 against view 1 and view 1 against view 0
            desc = desc + weights[term] * 0.5 * (loss_fn(desc0, desc1, targets[0], **kw) + loss_fn(desc1, desc0, targets[1], **kw))
        det0, det1 = detector_loss(logits0, batch["labels0"]), detector_loss(logits1, batch["labels1"])
        total = det0 + det1 + lc["desc_weight"] * desc
        losses = {"det0": det0, "det1": det1, "desc": desc}
        rep_weight = repeatability_weight(lc)
        if rep_weight > 0:
            if "flow01" not in batch:
                raise ValueError("loss.repeatability > 0 needs the pixel warps of depth supervision (data.supervision=depth)")
            s0, s1 = out["scores"][:b], out["scores"][b:]
            patch = int(lc.get("repeatability_patch", 8))
            rep = 0.5 * (repeatability_loss(s0, s1, batch["flow01"], patch=patch) + repeatability_loss(s1, s0, batch["flow10"], patch=patch))
            total = total + rep_weight * rep
            losses["rep"] = rep
        return {"loss": total, **losses}

    def training_step(self, batch, batch_idx):
        if "sim" in batch:  # data.real: simulated pairs and self-supervised pairs of real recordings in one batch
            batch = merge_batches(batch["sim"], warp_views(batch["real"]))
        for key in ("mcts0", "mcts1"):
            if not torch.isfinite(batch[key]).all():
                raise ValueError(f"non-finite values in batch {batch_idx} ({key}); the data pipeline should have rejected them")
        losses = self._losses(batch)
        if not torch.isfinite(losses["loss"]):
            # a diverging step is skipped and counted (logged as train/skipped_nonfinite), never averaged in
            self.skipped_nonfinite += 1
            self.log("train/skipped_nonfinite", float(self.skipped_nonfinite))
            if self.skipped_nonfinite > self.cfg["optim"].get("max_nonfinite_steps", 10):
                raise FloatingPointError(f"loss was non-finite in {self.skipped_nonfinite} steps ({ {k: float(v) for k, v in losses.items()} }); "
                                         "lower optim.lr or check the data")
            return None
        self.log_dict({f"train/{k}": v for k, v in losses.items()}, prog_bar=False, batch_size=batch["mcts0"].shape[0])
        self.log("loss", losses["loss"], prog_bar=True, logger=False, batch_size=batch["mcts0"].shape[0])
        return losses["loss"]

    # -- which parts learn: optim.train_only ---------------------------------------------------
    def frozen_parts(self) -> list[str]:
        """Top-level parts of the network (``encoder``, ``detector``, ``descriptor``, and ``detector_pixel`` where
        ``model.detector_pixel`` adds it) that this run keeps fixed.

        ``optim.train_only: [descriptor]`` fine-tunes the descriptor head alone: the keypoints (encoder and
        detector head, BatchNorm statistics included) stay bit-identical to the start weights, so a fine-tune
        can change what the descriptors match without moving where the keypoints are.
        """
        only = self.cfg["optim"].get("train_only")
        if only is None:
            return []
        only = [only] if isinstance(only, str) else list(only)
        parts = [name for name, _ in self.model.named_children()]
        unknown = [name for name in only if name not in parts]
        if unknown or not only:
            raise ValueError(f"optim.train_only must name some of {parts} (or be null: everything learns), got {only}")
        return [name for name in parts if name not in only]

    def model_trainable_parts(self) -> list[str] | None:
        """The parts that learn when some are frozen (recorded in ``model.pt``), else None."""
        frozen = self.frozen_parts()
        return [name for name, _ in self.model.named_children() if name not in frozen] if frozen else None

    def _freeze(self) -> None:
        for name in self.frozen_parts():
            part = getattr(self.model, name)
            part.requires_grad_(False)
            # eval mode: BatchNorm neither updates its running statistics nor normalises by the batch's
            part.eval()

    def on_fit_start(self):
        self._freeze()

    def on_train_batch_start(self, batch, batch_idx):
        # Lightning restores each submodule's mode after a validation; a callback or user code calling
        # .train() on the module would not, and BatchNorm in train mode would move the keypoints
        self._freeze()

    def configure_optimizers(self):
        frozen = set(self.frozen_parts())
        params = [p for name, part in self.model.named_children() if name not in frozen for p in part.parameters()]
        return torch.optim.Adam(params, lr=self.cfg["optim"]["lr"])

    # -- validation: the relative-pose protocol on held-out sequences ------------------------
    def validation_step(self, path, batch_idx):
        from aerovis_slam.errors import DataError

        from .eval.pose import evaluate_sequence

        vc = self.cfg["val"]
        cams = vc.get("cam", "cam0")
        det = TorchDetector(self.model, self.cfg["model"], device=self.device)
        # Both cameras by default: on the `train` preset only the held-out spin sequence rotates 45
        # degrees within 2 s, so one camera at 10 Hz gave 40 pairs of one sequence and the AUC@10 that
        # picks best.ckpt swung by 10 points between neighbouring epochs.
        for cam in [cams] if isinstance(cams, str) else list(cams):
            try:
                result = evaluate_sequence(path, det, cam=cam, mcts_kind=det.mcts_kind, mcts_params=det.mcts_params,
                                           rate_hz=vc["rate_hz"], max_pairs=vc["max_pairs"], progress=False)
            except DataError as exc:  # e.g. a validation sequence that never rotates 45 deg: no pairs to score
                if (path, cam) not in self._val_unusable:
                    self._val_unusable.add((path, cam))
                    rank_zero_warn(f"validation skips {exc}")
                continue
            self._val_pairs.extend(result["per_pair"])

    def on_validation_epoch_end(self):
        from .eval.pose import summarize

        if not self._val_pairs:
            rank_zero_warn("no validation pairs: val/auc10 is 0 (check data.val / val.max_pairs)")
            self.log("val/auc10", 0.0)
            return
        s = summarize(self._val_pairs)
        min_pairs = int(self.cfg["val"].get("min_pairs") or 0)
        if s["pairs"] < min_pairs and not self._warned_few_pairs:
            self._warned_few_pairs = True
            rank_zero_warn(f"validation scores only {s['pairs']} pairs (val.min_pairs={min_pairs}): val/auc10, which selects "
                           "best.ckpt, is noisy; add rotating sequences to data.val (or raise data.val_sequences, val.rate_hz, val.max_pairs)")
        self.log_dict({"val/auc5": s["auc5"], "val/auc10": s["auc10"], "val/auc20": s["auc20"], "val/auc10_max": s["auc10_max"],
                       "val/pairs": float(s["pairs"]), "val/matches": s["matches"]}, prog_bar=False)
        self.log("val_auc10", s["auc10"], prog_bar=True, logger=False)
        self._val_pairs = []
