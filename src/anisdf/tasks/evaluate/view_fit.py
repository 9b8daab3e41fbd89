"""Fitting a few numbers of one scored view to its image with the scene frozen: the view's pixels, the photometric
error both fits minimise, and the Adam loop of the appearance code (the camera correction is solved by
Levenberg-Marquardt, evaluate/view_cameras.py)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

import numpy as np
import torch


def view_pixels(h: int, w: int, device: torch.device, left_half: bool = False) -> torch.Tensor:
    """Indices of a view's ``h x w`` pixels (row-major), or of its left half (columns ``< w // 2``) only."""
    pixels = torch.arange(h * w, device=device)
    return pixels[(pixels % w) < w // 2] if left_half else pixels


@contextlib.contextmanager
def scene_frozen(model: torch.nn.Module) -> Iterator[None]:
    """The model's trainable parameters frozen (no gradients) inside the block and given back their gradients
    after, even when the block raises: a view's fit moves its own few numbers only."""
    frozen = [p for p in model.parameters() if p.requires_grad]
    for p in frozen:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in frozen:
            p.requires_grad_(True)


def photometric_error(render: Callable, batch) -> torch.Tensor:
    """Mean squared error of ``render(batch) -> RenderOutput`` against the batch's colours: what a fit minimises."""
    return torch.mean((render(batch).rgb.float() - batch.rgb) ** 2)


def fit_to_view(model, batch, pixels: torch.Tensor, params: list[torch.Tensor], render: Callable, steps: int,
                rays: int, lr: float, seed: int, final_lr: float = 1.0) -> None:
    """Adam on ``params`` (learning rate ``lr``, cosine to ``final_lr`` times it; 1: constant) for ``steps`` steps
    of ``rays`` pixels drawn at random from ``pixels`` (indices into ``batch``, a view's rays), minimising the mean
    squared error of ``render(rays) -> RenderOutput`` against their colours. The model's own parameters are frozen
    meanwhile and given back their gradients after."""
    opt = torch.optim.Adam(params, lr=lr)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda k: final_lr + (1 - final_lr) * 0.5 * (1 + np.cos(np.pi * k / steps)))
    gen = torch.Generator().manual_seed(seed)
    with scene_frozen(model):
        for _ in range(steps):
            pick = pixels[torch.randint(pixels.numel(), (min(rays, pixels.numel()),), generator=gen)
                          .to(pixels.device)]
            b = batch[pick]
            with torch.enable_grad():
                loss = photometric_error(render, b)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
