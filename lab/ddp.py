"""Training on many processes: DistributedDataParallel (DDP) under torchrun, handed to
train.train_stack as a Shard, the rows of each global batch this process holds.

Under torchrun every process (a rank) runs the same program. train_stack then splits each global
batch of cfg.batch_size scenarios over the world of W ranks, cfg.batch_size / W each, and wraps
the module it trains in DistributedDataParallel (DDP), which averages the ranks' gradients during
backward. That average is exactly the gradient of the single-process loss on the global batch (up
to the order floats are summed in) because:
  - the ranks' batches together are the single-process batch: every rank draws the same
    permutation of the data (same seed) and takes positions rank, rank + W, rank + 2W, ... of it
    (DistributedSampler, without its own shuffling), so step i's shards together are
    perm[i B:(i + 1) B], the single-process batch i;
  - every random draw is of the global batch: the decoder's sampled controls are drawn for all B
    rows on every rank (same seed) and each keeps its own rows (Shard.decoder_noise);
  - each rank's loss is its share of the global mean, scaled by W: DDP averages the ranks'
    gradients, so the rank's sum over its scenarios is divided by (global count / W), never by its
    own count. L_plan and L_ctr are means over the *plannable* scenarios, whose number differs
    from rank to rank: the global count is all-reduced;
  - the batch statistics inside L_pred (the KL free-bits test, the mutual information's mean
    p(z|x)) and the scenario weights' normaliser are taken over the global batch, by an all_reduce
    that autograd differentiates through (AllReduceSum: its backward sums the ranks' gradients),
    so each rank's parameters also get the other ranks' share of the gradient of those statistics.
With autograd-aware all_reduces inside the ranks' losses, what DDP minimises is the mean of the
ranks' losses (each a function of every rank's rows): here W x share / W = the single-process
loss. The gradients are then the same on every rank, so gradient clipping, Adam and the lr
schedule stay in step.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data.distributed import DistributedSampler


class AllReduceSum(torch.autograd.Function):
    """y = the sum of x over the ranks, on every rank, differentiable: y feeds every rank's loss,
    so the backward is the same all_reduce (torch.distributed.nn's, which torch 2.13 deprecates)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, group) -> torch.Tensor:
        ctx.group = group
        y = x.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(y, group=group)
        return y

    @staticmethod
    def backward(ctx, grad_y: torch.Tensor):
        return AllReduceSum.apply(grad_y, ctx.group), None


@dataclass(frozen=True)
class Shard:
    """The rows of a global batch this process holds: positions rank, rank + world, ... Shard():
    one process, the whole batch. group: the loss's all_reduces', apart from DDP's own."""

    rank: int = 0
    world: int = 1
    group: object = None

    @staticmethod
    def of_process_group() -> "Shard":
        """This process's shard under torchrun; Shard() in one process."""
        if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
            return Shard()
        return Shard(
            dist.get_rank(), dist.get_world_size(), dist.new_group(backend=dist.get_backend())
        )

    def check_split(self, batch_size: int) -> None:
        if batch_size % self.world:
            raise ValueError(
                f"cfg.batch_size: {batch_size} scenarios per step do not split evenly over "
                f"{self.world} processes; choose a multiple of {self.world} (--set batch_size=...) "
                "or another process count"
            )

    def mean(self, x: torch.Tensor) -> torch.Tensor:
        """x (b, ...) -> (...) its mean over the global batch, autograd-aware."""
        if self.world == 1:
            return x.mean(0)
        return AllReduceSum.apply(x.sum(0), self.group) / (self.world * len(x))

    def total(self, x: torch.Tensor) -> torch.Tensor:
        """x (b, ...) -> (...) its sum over the global batch, without gradient (counts, logs)."""
        s = x.detach().sum(0)
        if self.world > 1:
            dist.all_reduce(s, group=self.group)
        return s

    def decoder_noise(self, model, b: int, cfg, like: torch.Tensor):
        """The decoder's training noise (T, b, K, 2): this rank's rows of the global batch's draw;
        None where the decoder draws itself (one process, eval mode)."""
        if self.world == 1 or not model.training:
            return None
        K = cfg.pred_modes
        steps = []
        for _ in range(cfg.horizon):
            noise = torch.randn(b * self.world * K, 2, dtype=like.dtype, device=like.device)
            # global scenario rank + world j is this rank's scenario j
            steps.append(noise.view(b, self.world, K, 2)[:, self.rank])
        return torch.stack(steps)

    def positions(self, n: int) -> torch.Tensor:
        """(n // world,) this rank's positions in an ordering of n items (DistributedSampler,
        unshuffled: the permutation every rank draws alike is the shuffle)."""
        sampler = DistributedSampler(range(n), self.world, self.rank, shuffle=False, drop_last=True)
        # they index the permutation, drawn on the CPU
        return torch.tensor(list(sampler), dtype=torch.long, device="cpu")

    def close(self) -> None:
        if self.group is not None:
            dist.destroy_process_group(self.group)


def wrap(module: torch.nn.Module, shard: Shard) -> torch.nn.Module:
    """The module in one process, else DDP around it (rank 0's parameters, gradients averaged)."""
    return module if shard.world == 1 else DistributedDataParallel(module)
