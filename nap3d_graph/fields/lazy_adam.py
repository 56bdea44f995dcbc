"""Adam for the grid field's large, sparsely touched tensors: only the voxels a batch of
rays reached get a step (the others keep their moments), which is what makes a dense grid
train in minutes on a CPU."""

from __future__ import annotations

import torch

__all__ = ["LazyAdam"]


class LazyAdam:
    """Adam on the rows of a (V, C) grid table that a step touched ("lazy" Adam).

    Why not ``torch.optim.Adam``: a step touches a few percent of the grid's vertices, but a
    dense optimiser (and ``grid_sample``'s backward, which zero-fills a gradient the size of
    the grid) costs O(grid) per step -- most of a CPU step's time on a 3 cm room grid.
    Gradients are scattered here with ``index_add_`` and only touched rows are updated, so a
    step costs O(samples). Bias correction uses the global step, as ``torch.optim.SparseAdam``.
    Rows are vertices, so a (V, C) channels-last table keeps each update contiguous.
    """

    def __init__(self, table: torch.Tensor, lr: float, betas=(0.9, 0.99), eps: float = 1e-8):
        self.table = table  # (V, C), updated in place
        self.lr = lr
        self.beta1, self.beta2 = betas
        self.eps = eps
        self.grad = torch.zeros_like(table)
        self.m = torch.zeros_like(table)
        self.v = torch.zeros_like(table)
        self.touched = torch.zeros(table.shape[0], dtype=torch.bool, device=table.device)
        self.steps = 0

    def accumulate(self, idx: torch.Tensor, contrib: torch.Tensor) -> None:
        """Add gradient ``contrib`` (K, C) at vertex indices ``idx`` (K,)."""
        self.grad.index_add_(0, idx, contrib)
        self.touched[idx] = True

    def step(self, lr_scale: float = 1.0) -> None:
        rows = self.touched.nonzero()[:, 0]
        if rows.numel() == 0:
            return
        self.touched[rows] = False
        self.steps += 1
        g = self.grad[rows]
        self.grad[rows] = 0.0
        m = self.m[rows].mul_(self.beta1).add_(g, alpha=1.0 - self.beta1)
        v = self.v[rows].mul_(self.beta2).addcmul_(g, g, value=1.0 - self.beta2)
        self.m[rows] = m
        self.v[rows] = v
        bc1 = 1.0 - self.beta1 ** self.steps
        bc2 = 1.0 - self.beta2 ** self.steps
        update = (m / bc1).div_((v / bc2).sqrt_().add_(self.eps))
        self.table.index_add_(0, rows, update, alpha=-(self.lr * lr_scale))
