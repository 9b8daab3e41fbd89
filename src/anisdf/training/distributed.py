"""Data-parallel training with ``torch.distributed``, launched by ``torchrun`` (docs/distributed.md).

Each rank draws its own rays (a random stream per rank) and renders them; after the backward pass the gradients of
all ranks are averaged by one all-reduce of a flat buffer (the hash tables are dense parameters, so a flat buffer
costs no more than DDP's buckets, and the double backward of the eikonal term needs no DDP hooks). Every rank then
takes the same optimiser step on the same parameters, so the model stays identical everywhere. The occupancy grid is
computed by rank 0 and broadcast (a bit mask), so float noise between devices cannot make the grids differ. Losses
that are means over samples (eikonal, curvature) are weighted by each rank's share of the step's samples, so the
averaged gradient is the gradient of the loss over the union of the ranks' rays: a step of N ranks is one step of a
single process on N times the rays.

With one process none of this runs: the trainer keeps ``dist = None`` and its step is the single-process step.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as td
from torch import Tensor

from anisdf.errors import AnisdfError

log = logging.getLogger("anisdf")


def env_world_size() -> int:
    """``WORLD_SIZE`` as torchrun sets it (1 when not launched by torchrun)."""
    try:
        return int(os.environ.get("WORLD_SIZE", "1"))
    except ValueError:
        raise AnisdfError(f"WORLD_SIZE={os.environ['WORLD_SIZE']!r} is not an integer") from None


def rank_seed(seed: int, rank: int, step: int = 0) -> int:
    """Seed of rank ``rank``'s ray stream (``step``: a stream restarted at that step, when a resume changes the
    number of ranks); distinct for every (seed, rank, step), from numpy's SeedSequence."""
    return int(np.random.SeedSequence([seed, rank, step, 0x616E69]).generate_state(1, np.uint64)[0] >> 1)


@dataclass
class Dist:
    """This process's place in the job and the few collectives the trainer needs."""

    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    # ----------------------------------------------------------------------------------------- collectives
    def sum_counts(self, counts: Iterable[int]) -> list[int]:
        """Element-wise sum over ranks of a few integers (the step's sample counts)."""
        t = torch.tensor(list(counts), dtype=torch.int64, device=self.device)
        td.all_reduce(t)
        return [int(v) for v in t.tolist()]

    def average_grads(self, params: Iterable[Tensor], stats: Tensor) -> Tensor:
        """Average the gradients of ``params`` over ranks in place and return ``stats`` (a float vector) averaged too,
        in one all-reduce. A parameter no rank has a gradient for keeps none (AdamW then leaves it alone, as one
        process would); one that only some ranks have a gradient for gets the average with zeros elsewhere."""
        params = [p for p in params if p.requires_grad]
        flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1).float()
                          for p in params]
                         + [torch.tensor([float(p.grad is not None) for p in params], device=self.device),
                            stats.float().reshape(-1)])
        td.all_reduce(flat)
        flat /= self.world_size
        n_grads = flat.numel() - len(params) - stats.numel()
        has = flat[n_grads : n_grads + len(params)].tolist()
        offset = 0
        for p, h in zip(params, has, strict=True):
            n = p.numel()
            if h > 0:
                g = flat[offset : offset + n].view_as(p).to(p.dtype)
                if p.grad is None:
                    p.grad = g.clone()
                else:
                    p.grad.copy_(g)
            offset += n
        return flat[n_grads + len(params) :]

    def broadcast_module(self, module: torch.nn.Module) -> None:
        """Rank 0's parameters and buffers on every rank (after building the model)."""
        self.broadcast_tensors([*module.parameters(), *module.buffers()])

    def broadcast_tensors(self, tensors: list[torch.Tensor]) -> None:
        """Rank 0's values of ``tensors`` on every rank, in place."""
        for t in tensors:
            if t.dtype == torch.bool:  # not every backend sends bool tensors
                u = t.data.to(torch.uint8)
                td.broadcast(u, src=0)
                t.data.copy_(u.bool())
            else:
                td.broadcast(t.data, src=0)

    def broadcast_float(self, value: float) -> float:
        """Rank 0's ``value`` (e.g. the time spent, which the time-budget schedule reads) on every rank."""
        t = torch.tensor([value], dtype=torch.float64, device=self.device)
        td.broadcast(t, src=0)
        return float(t.item())

    def gather_generator_states(self, generator: torch.Generator) -> list[Tensor] | None:
        """Every rank's generator state, on rank 0 (None elsewhere): what a resume with as many ranks restores."""
        states: list[Tensor | None] = [None] * self.world_size
        td.all_gather_object(states, generator.get_state())
        return [s for s in states if s is not None] if self.is_main else None


def init_from_env(device_name: str) -> Dist | None:
    """Join the job torchrun started (``WORLD_SIZE`` > 1): NCCL with one GPU per rank (``cuda:LOCAL_RANK``) when
    ``device_name`` is ``auto`` or ``cuda`` and CUDA is there, gloo on CPUs. None without torchrun (one process)."""
    world = env_world_size()
    if world <= 1:
        return None
    rank, local = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    name = device_name or "auto"
    if name not in ("auto", "cpu", "cuda"):
        raise AnisdfError(f"--device {name}: under torchrun each rank takes cuda:LOCAL_RANK; pass auto, cuda or cpu")
    use_cuda = name == "cuda" or (name == "auto" and torch.cuda.is_available())
    if use_cuda:
        if not torch.cuda.is_available():
            raise AnisdfError("--device cuda: CUDA is not available in this torch build")
        if local >= torch.cuda.device_count():
            raise AnisdfError(f"rank {rank}: LOCAL_RANK {local} but this node has {torch.cuda.device_count()} "
                              "GPU(s); start at most one process per GPU (torchrun --nproc-per-node)")
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
    else:
        device = torch.device("cpu")
    if not td.is_initialized():
        td.init_process_group(backend="nccl" if use_cuda else "gloo",
                              **({"device_id": device} if use_cuda else {}))
    if rank == 0:
        log.info("distributed training: %d ranks (%s)", world, td.get_backend())
    return Dist(rank=rank, world_size=world, local_rank=local, device=device)


def shutdown(ctx: Dist | None, *, finished: bool) -> None:
    """Leave the process group (on every rank). After a run that ``finished``, the ranks first wait for each other:
    a rank that tore down its gloo connections while another still wrote its last files could abort the other
    ("terminate called without an active exception"). After an error no rank waits (the others may never come)."""
    if ctx is None or not td.is_initialized():
        return
    if finished:
        td.barrier()
    td.destroy_process_group()
