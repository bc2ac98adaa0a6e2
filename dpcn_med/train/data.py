"""Training data: volumes on the solver's canonical grid, and the pairs made from them.

Synthetic pairs (:func:`dpcn_med.synth.synthetic_pairs`) are made on the training device, a batch at a time, from
base volumes held there as one ``(V, 1, N, N, N)`` tensor; they are prepared exactly as :func:`dpcn_med.register`
prepares its inputs, so the networks see at training what they see at inference.
"""

from __future__ import annotations

import torch
from torch import Tensor

from dpcn_med.errors import InputError
from dpcn_med.preprocess import CanonicalGrid, Preprocessing, prepare, resample_to_grid, to_tensor
from dpcn_med.solver import PoseTarget
from dpcn_med.synth import PairConfig, synthetic_pairs


def load_volume(name: str):
    """A built-in volume by name (``mni``, ``mni-head``, ``mni-pseudo-ct``) or an image file."""
    from dpcn_med import io, samples

    built_in = {"mni": samples.mni152_t1, "mni-head": samples.mni152_head_t1, "mni-pseudo-ct": samples.mni152_pseudo_ct}
    return built_in[name]() if name in built_in else io.read_image(name)


def canonical_volume(image, size: int, preprocessing: Preprocessing | None = None) -> Tensor:
    """``(1, 1, N, N, N)`` float32: ``image`` prepared as :func:`dpcn_med.register` prepares it (modality window,
    foreground outline), on its own canonical cube (foreground diagonal spanning ``preprocessing.fill``)."""
    preprocessing = preprocessing or Preprocessing()
    prepared = prepare(image, config=preprocessing)
    grid = CanonicalGrid(size, prepared.diagonal / (preprocessing.fill * size), tuple(map(float, prepared.centre)))
    return to_tensor(resample_to_grid(prepared.image, grid))


def volume_bank(names: tuple[str, ...], size: int, preprocessing: Preprocessing | None = None,
                device: str | torch.device = "cpu", key: str = "data.volumes") -> Tensor:
    """``(V, 1, N, N, N)``: every named volume on its canonical cube, on ``device``; ``key`` names the list in
    messages.

    Raises:
        InputError: no volumes, or one that cannot be read (the message names it).
    """
    if not names:
        raise InputError(f"{key}: no volumes to make pairs from")
    return torch.cat([canonical_volume(load_volume(name), size, preprocessing) for name in names]).to(device)


def sample_pairs(bank: Tensor, batch: int, generator: torch.Generator, config: PairConfig
                 ) -> tuple[Tensor, Tensor, PoseTarget]:
    """A batch of synthetic pairs from randomly chosen base volumes of ``bank`` (on ``bank``'s device)."""
    index = torch.randint(len(bank), (batch,), generator=generator, device=generator.device)
    return synthetic_pairs(bank[index.to(bank.device)], generator, config)


def validation_set(bank: Tensor, count: int, seed: int, config: PairConfig, *, batch: int = 16
                   ) -> list[tuple[Tensor, Tensor, PoseTarget]]:
    """The same ``count`` pairs for every call with the same arguments, in batches of at most ``batch``."""
    generator = torch.Generator(device=bank.device).manual_seed(seed)
    batches, left = [], count
    while left > 0:
        size = min(batch, left)
        batches.append(sample_pairs(bank, size, generator, config))
        left -= size
    return batches
