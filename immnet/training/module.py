"""The two-stage curriculum as LightningModules (docs/spec.md section 4).

* ``Stage1Module``: every expert alone (its own posterior is its estimate), each on a batch of 60 %
  trajectories of its own mode and 40 % maneuvering ones; state loss only; only the gain networks train.
* ``Stage2Module``: IMMNet end to end, ``gamma * state loss + (1 - gamma) * CE(mode)``, starting from
  a stage-1 checkpoint's experts; optionally ``+ expert_weight *`` each expert's state loss on the
  scans of its own mode (``own_mode_loss``; 0, the paper's loss, by default).

Both use truncated back-propagation through time: a 400-step sequence is cut into chunks of
``tbptt`` steps, each chunk is a backward pass and an optimizer step, and the carry is detached
between chunks. Gradients are clipped; a chunk whose loss or gradient is not finite is skipped and
counted (``train/skipped``).
"""

from __future__ import annotations

import math
from pathlib import Path

import lightning as L
import torch

from immnet import keys
from immnet.choice import spelled
from immnet.checkpoints import add_checksum, verify_checksum
from immnet.evaluation.metrics import confusion, per_trajectory_rmse, position_error
from immnet.stages import IMMNet
from immnet.stages.network import net_arguments
from immnet.tracking.tracker import read_checkpoint
from immnet.training.losses import component_weights, mode_loss, own_mode_loss, state_loss

AXES = ("x", "y", "z")


def position_rmse(est: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Per-axis position RMSE of docs/spec.md section 5 (``immnet.evaluation.metrics``), ``[3]``."""
    return per_trajectory_rmse(position_error(est.detach(), truth)).mean(0)


class _TrackerModule(L.LightningModule):
    def __init__(
        self,
        net: IMMNet | None = None,  # or its arguments as a mapping (Python; old checkpoints)
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        tbptt: int = 20,
        grad_clip: float = 1.0,
        loss_weights: tuple[float, float, float] = (1.0, 0.1, 0.02),
        lr_schedule: str = "constant",
        lr_floor: float = 0.05,
    ):
        super().__init__()
        self.save_hyperparameters()
        self.automatic_optimization = False
        # the network as typed components (LightningCLI: ``net: {class_path: immnet.stages.IMMNet, init_args:
        # ...}``, each argument overridable on its own; docs/configs.md) or its arguments as a mapping
        self.net = net if isinstance(net, IMMNet) else IMMNet(**net_arguments(net))
        if isinstance(self.hparams.get("net"), torch.nn.Module):  # built in Python: keep plain data, not the module
            self.hparams["net"] = self.net.config
        elif isinstance(self.hparams.get("net"), dict):  # a setting given as its type is kept as its spelling
            self.hparams["net"] = spelled(self.hparams["net"])
        self.register_buffer("w_state", component_weights(*loss_weights), persistent=False)
        self.skipped = 0
        if lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"lr_schedule must be 'constant' or 'cosine', got {lr_schedule!r}")
        if not 0.0 <= lr_floor <= 1.0:
            raise ValueError(f"lr_floor must be in [0, 1], got {lr_floor}")

    def _train_only(self, params) -> None:
        """Freeze every parameter of the network but ``params`` (``requires_grad`` off: out of the optimizer and the
        gradient clip)."""
        keep = {id(p) for p in params}
        for p in self.net.parameters():
            p.requires_grad_(id(p) in keep)

    def trainable_parameters(self):
        """The parameters the optimizer and the gradient clip see: those that require a gradient (a stage may freeze
        some: stage 1 all but the gain's, ``Stage2Module(learn=...)`` all but the named components')."""
        return (p for p in self.parameters() if p.requires_grad)

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Every checkpoint carries the SHA-256 of its weights (``immnet.checkpoints``, docs/checkpoints.md)."""
        add_checksum(checkpoint)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Refuse weights that disagree with their checksum, whichever reader Lightning was given."""
        trainer = self._trainer
        verify_checksum(checkpoint, (trainer.ckpt_path if trainer is not None else None) or "the checkpoint")

    def configure_optimizers(self):
        """Adam; with ``lr_schedule: cosine`` the rate falls per optimizer step from ``lr`` to
        ``lr_floor * lr`` along a half cosine over ``trainer.max_steps``."""
        opt = torch.optim.Adam(self.trainable_parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        if self.hparams.lr_schedule == "constant":
            return opt
        total = self.trainer.max_steps
        if total is None or total <= 0:
            raise ValueError("lr_schedule: cosine needs trainer.max_steps > 0 (the length of the schedule)")
        floor = self.hparams.lr_floor

        def factor(step: int) -> float:
            return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * min(step, total) / total))

        return {"optimizer": opt, "lr_scheduler": torch.optim.lr_scheduler.LambdaLR(opt, factor)}

    def _optimize(self, loss: torch.Tensor) -> bool:
        """One optimizer step on ``loss`` (a TBPTT chunk); skipped, and counted, when the loss or
        the gradient is not finite.

        Several backward passes make one training step here, so under DDP the gradients are
        averaged by one all-reduce per chunk rather than by DDP's reducer (which expects a single
        backward per forward and every parameter in each: the learned initial GRU states only
        enter a sequence's first chunk). A non-finite loss still runs its backward there, so that
        every rank joins the all-reduce, and the NaN it spreads makes every rank skip together.
        """
        opt = self.optimizers()
        distributed = self._trainer is not None and self.trainer.world_size > 1
        if not distributed and not torch.isfinite(loss):
            self.skipped += 1
            return False
        opt.zero_grad(set_to_none=True)
        if distributed:
            with self.trainer.strategy.block_backward_sync():
                self.manual_backward(loss)
            self._average_gradients()
        else:
            self.manual_backward(loss)
        norm = torch.nn.utils.clip_grad_norm_(list(self.trainable_parameters()), self.hparams.grad_clip)
        if not torch.isfinite(norm):
            opt.zero_grad(set_to_none=True)
            self.skipped += 1
            return False
        opt.step()
        sched = self.lr_schedulers() if self._trainer is not None else None
        if sched is not None:
            sched.step()
        return True

    def _average_gradients(self) -> None:
        """Average the gradients over ranks, one all-reduce of one flat buffer."""
        params = [p for p in self.trainable_parameters() if p.grad is not None]
        if not params:
            return
        flat = torch.cat([p.grad.reshape(-1) for p in params])
        torch.distributed.all_reduce(flat)
        flat /= self.trainer.world_size
        offset = 0
        for p in params:
            n = p.grad.numel()
            p.grad.copy_(flat[offset : offset + n].view_as(p.grad))
            offset += n

    def chunks(self, T: int):
        step = self.hparams.tbptt if self.hparams.tbptt and self.hparams.tbptt > 0 else T
        return [(s, min(s + step, T)) for s in range(0, T, step)]

    def _log_rmse(self, prefix: str, est, truth, batch_size):
        rmse = position_rmse(est, truth)
        for a, v in zip(AXES, rmse):
            self.log(f"{prefix}/rmse_{a}", v, batch_size=batch_size, sync_dist=True)
        self.log(f"{prefix}/rmse_avg", rmse.mean(), batch_size=batch_size, prog_bar=True, sync_dist=True)


class Stage1Module(_TrackerModule):
    """Stage 1: experts alone. Batches are TensorDicts ``[M, B]`` (expert ``i``'s mix on row ``i``)."""

    def __init__(self, net: IMMNet | None = None, lr: float = 1e-2, **kwargs):
        super().__init__(net=net, lr=lr, **kwargs)
        self._train_only(self.net.gain.parameters())  # the rest frozen, so that DDP finds no unused parameter

    def training_step(self, batch, batch_idx):
        M = self.net.n_experts
        if batch.batch_dims == 1:  # no own-mode mix (e.g. a single expert on maneuvering data)
            batch = batch.unsqueeze(0).expand(M, *batch.batch_size)
        if batch.batch_dims != 2 or batch.batch_size[0] != M:
            raise ValueError(f"stage 1 needs batches [M={M}, B] (one row per expert) or [B], got {tuple(batch.batch_size)}")
        z = batch[keys.MEASUREMENTS].transpose(0, 1)  # [B, M, T, 3]
        x = batch[keys.STATES].transpose(0, 1).transpose(1, 2)  # [B, T, M, 9]
        r = batch[keys.R].transpose(0, 1)  # [B, M]
        carry, total = None, 0.0
        for s, e in self.chunks(z.shape[-2]):
            out, carry = self.net.rollout(z[..., s:e, :], carry, experts_alone=True)
            loss = state_loss(out[keys.STATE], x[:, s:e], r, self.w_state)
            self._optimize(loss)
            carry = carry.detach()
            total += loss.detach() * (e - s)
        self.log("train/loss", total / z.shape[-2], prog_bar=True, batch_size=z.shape[0])
        self.log("train/skipped", float(self.skipped))

    def validation_step(self, batch, batch_idx):
        M = self.net.n_experts
        z = batch[keys.MEASUREMENTS].unsqueeze(1).expand(-1, M, -1, -1)
        x = batch[keys.STATES].unsqueeze(2).expand(-1, -1, M, -1)
        out, _ = self.net.rollout(z, experts_alone=True)
        loss = state_loss(out[keys.STATE], x, batch[keys.R].unsqueeze(1).expand(-1, M), self.w_state)
        self.log("val/loss", loss, prog_bar=True, batch_size=z.shape[0], sync_dist=True)
        est = out[keys.STATE]
        for i, name in enumerate(self.net.model_set.names):
            rmse = position_rmse(est[:, :, i], batch[keys.STATES])
            self.log(f"val/rmse_avg_{name}", rmse.mean(), batch_size=z.shape[0], sync_dist=True)


def widen_for_interval(weights: dict, own: dict, columns: dict[str, int]) -> dict:
    """``weights`` of a network without the interval input, for one that reads it: each weight in ``columns``
    (name -> the interval's input column) that lacks exactly that column gets it as zeros. The widened
    network computes what the checkpoint's does at any interval until training moves the new column
    (function-preserving); the other weights are returned as they are."""
    return _widen(weights, own, columns,
                  lambda w, target, col: w.shape[:-1] == target.shape[:-1] and w.shape[-1] + 1 == target.shape[-1],
                  lambda w, col: torch.cat([w[..., :col], w.new_zeros(*w.shape[:-1], 1), w[..., col:]], -1))


def _widen(weights: dict, own: dict, how: dict, fits, widen) -> dict:
    """``weights`` with each weight named in ``how`` whose shape differs from ``own``'s and ``fits(w, target,
    how[name])`` replaced by ``widen(w, how[name])``; a weight that does not fit is left for ``load_state_dict`` to
    name the mismatch."""
    out = dict(weights)
    for name, arg in how.items():
        w, target = out.get(name), own.get(name)
        if w is not None and target is not None and w.shape != target.shape and fits(w, target, arg):
            out[name] = widen(w, arg)
    return out


def _same_setting(own: torch.Tensor, stored: torch.Tensor) -> bool:
    """Whether a buffer built from ``net``'s settings is the one a checkpoint stores: equal in the file's precision,
    and for floating-point buffers in float32 (a network trained in float32 stores its float64 buffers rounded so)."""
    if torch.equal(own.to(stored.dtype), stored):
        return True
    return own.is_floating_point() and stored.is_floating_point() and torch.equal(own.float(), stored.float())


def widen_for_groups(weights: dict, own: dict, rows: dict[str, int]) -> dict:
    """``weights`` of a network with one joint set of modes, for one with modes per group: each weight in ``rows``
    (name -> the number of groups ``G``) that has ``1 / G`` of the rows gets them once per group. Each group then
    starts with the joint network's correction of the mode update; the other weights are returned as they are."""
    return _widen(weights, own, rows,
                  lambda w, target, groups: w.shape[1:] == target.shape[1:] and w.shape[0] * groups == target.shape[0],
                  lambda w, groups: w.repeat(groups, *([1] * (w.dim() - 1))))


class Stage2Module(_TrackerModule):
    """Stage 2: IMMNet end to end, ``gamma * MSE + (1 - gamma) * CE [+ expert_weight * own-mode MSE]``.

    ``expert_weight`` (default 0: the paper's loss) adds each expert's own state loss on the scans of
    the mode it stands for. End to end, only the fused estimate is scored, and stage 2 trades an
    expert's accuracy on its own mode for the mix (the CA expert alone on CA flight went from 1.09x
    to 1.14x the bound); this term keeps the experts experts (docs/immnet.md).

    ``init_checkpoint`` starts from a whole IMMNet instead (a stage-2 checkpoint or exported weights,
    such as the shipped ones): fine-tuning. Settings that only shape the computation (the interaction's
    ``p_stay``, the guard) come from ``net``, so a fine-tune can change them; one the checkpoint stores
    as a buffer (the classifier's ``p_stay``) must match it.

    ``init_parameters`` starts from the learned parameters alone of a trained IMMNet (each of the same name and
    shape), every buffer as ``net`` builds it: a network with other models, noise or chain (the filter experts'
    base) that keeps another network's KalmanNet and Transformer weights, e.g. ``recipes/real-imm-base.yaml``.

    ``learn`` names the components that learn (``gain``, ``classifier``, ``correction``: ``IMMNet``'s arguments;
    default all); every other parameter is frozen (``requires_grad`` off, out of the optimizer and the gradient
    clip), so a trained network keeps its weights while a stage added to it learns, e.g. an output correction on
    the shipped general network (``recipes/general-output.yaml``: ``init_checkpoint`` and ``learn: [correction]``).
    """

    def __init__(
        self,
        net: IMMNet | None = None,
        stage1_checkpoint: str | None = None,
        init_checkpoint: str | None = None,
        init_parameters: str | None = None,
        lr: float = 1e-3,
        gamma: float = 0.7,
        expert_weight: float = 0.0,
        learn: list[str] | None = None,
        **kwargs,
    ):
        super().__init__(net=net, lr=lr, **kwargs)
        if learn is not None:
            self._freeze_all_but(list(learn))
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not (math.isfinite(expert_weight) and expert_weight >= 0.0):
            raise ValueError(f"expert_weight must be finite and >= 0, got {expert_weight}")
        given = [n for n, v in (("stage1_checkpoint", stage1_checkpoint), ("init_checkpoint", init_checkpoint),
                                ("init_parameters", init_parameters)) if v]
        if len(given) > 1:
            raise ValueError(f"give one of stage1_checkpoint (the experts), init_checkpoint (the whole IMMNet) or "
                             f"init_parameters (its learned parameters), not {' and '.join(given)}")
        if stage1_checkpoint:
            self.load_experts(stage1_checkpoint)
        if init_checkpoint:
            self.load_net(init_checkpoint)
        if init_parameters:
            self.load_parameters(init_parameters)

    def _freeze_all_but(self, learn: list[str]) -> None:
        """``learn``: freeze every parameter outside the named components (a ValueError naming an unknown one, or
        one this network lacks or that has no parameters)."""
        parts = IMMNet.PARTS
        unknown = [c for c in learn if c not in parts]
        if unknown or not learn:
            raise ValueError(f"learn: unknown component(s) {unknown or learn!r}; choose from {', '.join(parts)}")
        has = self.net.learned_parts()
        empty = [c for c in learn if c not in has]
        if empty:
            raise ValueError(f"learn: this IMMNet's {', '.join(empty)} has no parameters to learn")
        self._train_only(p for c in learn for p in self.net.part(c).parameters())

    def load_parameters(self, path: str):
        """Start from the learned parameters of a trained IMMNet: every parameter of this network from the
        checkpoint's of the same name and shape (a ValueError naming those it lacks or shapes otherwise), widened
        as ``load_net`` widens them (the interval's input column, modes per group); the buffers stay as ``net``
        builds them (the models, the noise, the chain)."""
        _, net = read_checkpoint(path)
        own = dict(self.net.named_parameters())
        net = widen_for_interval(net, own, self.net.interval_columns())
        net = widen_for_groups(net, own, self.net.group_rows())
        missing = sorted(n for n in own if n not in net)
        shaped = sorted(n for n in own if n in net and tuple(net[n].shape) != tuple(own[n].shape))
        if missing or shaped:
            raise ValueError(f"{path} does not hold this IMMNet's parameters: missing {missing[:3]}, other shapes "
                             f"{shaped[:3]}")
        with torch.no_grad():
            for name, p in own.items():
                p.copy_(net[name].to(p.dtype))

    def load_net(self, path: str):
        """Start from every weight of a trained IMMNet (same model set and architecture). A checkpoint trained
        without the interval input starts a network that reads it: its weights fill the other columns and the
        interval's column starts at zero (``widen_for_interval``); one with one joint set of modes starts a network
        with modes per group, each group's logits from the joint ones (``widen_for_groups``); one without an output
        correction starts a network with one, the correction as built (the checkpoint's network until it learns)."""
        _, net = read_checkpoint(path)
        if not net:
            raise ValueError(f"{path} holds no IMMNet weights (net.*)")
        if self.net.correct is not None and not any(k.startswith("correct.") for k in net):
            # a network without an output correction starts one with it: the correction as built (its last layer
            # zero: the network is the checkpoint's until it learns)
            net = {**net, **{f"correct.{k}": v for k, v in self.net.correct.state_dict().items()}}
        # buffers are built from settings (the classifier's Markov prior from its p_stay, ...): a checkpoint
        # that stores other values was trained with other settings, which loading would bring back silently
        kept = self.net.state_dict()  # the persistent buffers: what a checkpoint stores
        own = {k: b.clone() for k, b in self.net.named_buffers() if k in kept}
        net = widen_for_interval(net, kept, self.net.interval_columns())
        net = widen_for_groups(net, kept, self.net.group_rows())
        try:
            self.net.load_state_dict(net)
        except RuntimeError as err:
            raise ValueError(f"checkpoint {path} does not match this IMMNet: {err}") from None
        differ = [k for k in sorted(own.keys() & net.keys()) if not _same_setting(own[k], net[k])]
        if differ:
            raise ValueError(f"checkpoint {path} was trained with other settings than `net` gives: its buffers {differ} differ "
                             "(set net's settings to the checkpoint's)")

    def load_experts(self, path: str):
        """Start from the gain networks of a stage-1 checkpoint (same model set)."""
        _, net = read_checkpoint(path)
        gain = {k[len("gain."):]: v for k, v in net.items() if k.startswith("gain.")}
        if not gain:
            raise ValueError(f"{path} holds no gain-network weights (net.gain.*)")
        missing, unexpected = self.net.gain.load_state_dict(gain, strict=False)
        if unexpected or [m for m in missing if not m.startswith("K_")]:
            raise ValueError(f"stage-1 checkpoint {path} does not match this model set: missing {missing}, unexpected {unexpected}")

    def losses(self, out, batch, s: int = 0, e: int | None = None):
        e = e if e is not None else out.batch_size[1] + s
        truth, r, mode = batch[keys.STATES][:, s:e], batch.get(keys.R, None), batch[keys.MODE][:, s:e]
        mse = state_loss(out[keys.STATE], truth, r, self.w_state)
        ce = mode_loss(self.net.to_mode_probs(out[keys.ROLLOUT_EXPERT_PROBS]), mode)
        g, w = self.hparams.gamma, self.hparams.expert_weight
        loss = g * mse + (1 - g) * ce
        own = torch.zeros_like(mse)
        if w > 0:
            own = own_mode_loss(out[keys.ROLLOUT_EXPERT_POST], truth, mode, self.net.model_set.modes, r, self.w_state)
            loss = loss + w * own
        return loss, mse, ce, own

    def training_step(self, batch, batch_idx):
        z = batch[keys.MEASUREMENTS]
        intervals = self.net.intervals_for(batch)  # None at the network's own dt
        carry, tot = None, z.new_zeros(4)  # on the batch's device, where the losses are
        told = self.net.told_r(batch)  # each track's r, where the filter experts are told it
        cov = self.net.told_cov(batch)  # each detection's covariance, where they are told it
        for s, e in self.chunks(z.shape[1]):
            out, carry = self.net.rollout(z[:, s:e], carry, intervals=None if intervals is None else intervals[:, s:e],
                                          r=told, meas_cov=None if cov is None else cov[:, s:e])
            parts = self.losses(out, batch, s, e)
            self._optimize(parts[0])
            carry = carry.detach()
            tot += torch.stack([p.detach() for p in parts]) * (e - s)
        tot /= z.shape[1]
        B = z.shape[0]
        self.log("train/loss", tot[0], prog_bar=True, batch_size=B)
        self.log("train/mse", tot[1], batch_size=B)
        self.log("train/ce", tot[2], batch_size=B)
        if self.hparams.expert_weight > 0:
            self.log("train/own_mode_mse", tot[3], batch_size=B)
        self.log("train/skipped", float(self.skipped))

    def validation_step(self, batch, batch_idx):
        self._score(batch, batch_idx, "val")

    def on_validation_epoch_end(self):
        """Log the validation confusion matrix as a figure (W&B), beside the scalar metrics."""
        self._log_confusion("val", f"validation, step {self.global_step}")

    def test_step(self, batch, batch_idx):
        self._score(batch, batch_idx, "test")

    def _score(self, batch, batch_idx, prefix: str) -> None:
        """A validation or test batch: its metrics logged (``_evaluate``), its confusion counts added to the epoch's."""
        probs = self._evaluate(batch, prefix)
        conf = confusion(probs.detach().cpu(), batch[keys.MODE].cpu())
        self._confusion = conf if batch_idx == 0 else self._confusion + conf

    def on_test_epoch_end(self):
        """``immnet test``: the test set's confusion matrix as a figure (W&B), beside the scalar metrics."""
        self._log_confusion("test", "test set")

    def _log_confusion(self, prefix: str, title: str) -> None:
        from lightning.pytorch.loggers import WandbLogger

        if self.trainer.sanity_checking or not isinstance(self.logger, WandbLogger) or not hasattr(self, "_confusion"):
            return
        from immnet.evaluation.figures import plot_confusion

        path = plot_confusion(self._confusion, Path(self.logger.save_dir or ".") / "figures" / f"confusion-{prefix}-{self.global_step}.png",
                              title=title)
        self.logger.log_image(key=f"{prefix}/confusion", images=[str(path)], step=self.global_step)

    def _evaluate(self, batch, prefix):
        out, _ = self.net.rollout(batch[keys.MEASUREMENTS], intervals=self.net.intervals_for(batch),
                                  r=self.net.told_r(batch), meas_cov=self.net.told_cov(batch))
        loss, mse, ce, own = self.losses(out, batch)
        B = batch.batch_size[0]
        self.log(f"{prefix}/loss", loss, prog_bar=True, batch_size=B, sync_dist=True)
        self.log(f"{prefix}/ce", ce, batch_size=B, sync_dist=True)
        if self.hparams.expert_weight > 0:
            self.log(f"{prefix}/own_mode_mse", own, batch_size=B, sync_dist=True)
        self._log_rmse(prefix, out[keys.STATE], batch[keys.STATES], B)
        probs = self.net.to_mode_probs(out[keys.ROLLOUT_EXPERT_PROBS])
        labelled = batch[keys.MODE] >= 0
        if labelled.any():  # real flights carry no mode labels
            hit = (probs.argmax(-1) == batch[keys.MODE])[labelled]
            self.log(f"{prefix}/mode_accuracy", hit.float().mean(), batch_size=B, sync_dist=True)
        return probs
