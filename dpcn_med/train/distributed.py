"""One process per device under ``torchrun`` (NCCL on CUDA, gloo on CPU), or a single process without it."""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist

from dpcn_med.devices import resolve_device
from dpcn_med.errors import InputError


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

    ``device``: ``auto`` takes ``cuda:LOCAL_RANK`` when CUDA is there, else the CPU; ``cuda`` takes
    ``cuda:LOCAL_RANK``; ``cpu`` and ``cuda:N`` are taken as they are.

    Raises:
        InputError: an unknown device, a CUDA device this machine does not have, or ``cuda:N`` for several processes
            (before anything else is done).
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local_rank = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    chosen = resolve_device(device)
    use_cuda = chosen.type == "cuda"
    if use_cuda:
        # Every process of a machine on one GPU: NCCL fails ("Duplicate GPU"); one process per machine may name it.
        local = int(os.environ.get("LOCAL_WORLD_SIZE", str(world_size)))
        if chosen.index is not None and local > 1:
            raise InputError(f"device {device!r} names one GPU for all {local} processes of torchrun on this machine; "
                             "use 'cuda' (each process takes cuda:LOCAL_RANK) or 'auto'")
        if chosen.index is None:
            chosen = torch.device(f"cuda:{local_rank}")
        if chosen.index >= torch.cuda.device_count():
            raise InputError(f"device {device!r}: there is no {chosen}; this machine has "
                             f"{torch.cuda.device_count()} CUDA device(s), from cuda:0")
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
