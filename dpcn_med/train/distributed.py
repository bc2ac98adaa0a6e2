"""One process per device under ``torchrun`` (NCCL on CUDA, gloo on CPU), or a single process without it."""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class Process:
    """This process's place in the run."""

    rank: int = 0
    world_size: int = 1
    device: torch.device = torch.device("cpu")

    @property
    def main(self) -> bool:
        """Rank 0 logs, validates and writes the checkpoints."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def start(device: str = "auto") -> Process:
    """Join the process group that ``torchrun`` (or the caller) described in ``RANK``, ``WORLD_SIZE``,
    ``LOCAL_RANK``, ``MASTER_ADDR`` and ``MASTER_PORT``; a plain single process without them.

    ``device``: ``auto`` takes ``cuda:LOCAL_RANK`` when CUDA is there, else the CPU.
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local_rank = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    use_cuda = device.startswith("cuda") or (device == "auto" and torch.cuda.is_available())
    chosen = torch.device(f"cuda:{local_rank}" if use_cuda and device in ("auto", "cuda") else
                          device if use_cuda else "cpu")
    if use_cuda:
        torch.cuda.set_device(chosen)
    if world_size > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if use_cuda else "gloo", rank=rank, world_size=world_size)
    return Process(rank=rank, world_size=world_size, device=chosen)


def stop(process: Process) -> None:
    """Leave the process group (after a last barrier, so no rank exits while another still writes)."""
    if process.distributed and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def barrier(process: Process) -> None:
    if process.distributed:
        dist.barrier()
