"""Training throughput and inference time of the DPCN++ network; prints a table and writes it under docs/.

Training: pairs per second of whole steps (synthetic pairs made on the device, forward, the six-term loss,
backward, AdamW), median over ``--steps`` after two warm-up steps, at each bandwidth and batch size. Inference: one
pair end to end through the trained-shape network (four UNets and the solver with its refinement), median over
``--repeats`` (CUDA events on the GPU), beside the learning-free solver on the same pair in the same process.

    python benchmarks/learned_speed.py --device cuda --bandwidths 32 64 --batches 32 64
    python benchmarks/learned_speed.py --device cpu --bandwidths 16 --batches 4 --steps 3   # a quick check
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from markdown import count_type, generated_by, publish  # noqa: E402  (the scripts' shared helpers)
from solver_speed import _elapsed  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CHANNELS = (16, 32, 64, 128)
"""The shipped configs' UNet channels (training/configs/*.yaml)."""


def measure(device: torch.device, bandwidth: int, batches: list[int], steps: int, repeats: int, amp: bool) -> dict:
    from dpcn_med.models import DPCN, ModelConfig, pose_loss
    from dpcn_med.preprocess import solver_grid
    from dpcn_med.samples import mni152_t1
    from dpcn_med.solver import solve
    from dpcn_med.synth import PairConfig, synthetic_pairs

    size = 2 * bandwidth
    base = solver_grid(mni152_t1(), size)[0].to(device)
    model = DPCN(ModelConfig(bandwidth=bandwidth, channels=CHANNELS)).to(device)
    optimiser = torch.optim.AdamW(model.parameters(), lr=1e-4)
    generator = torch.Generator(device=device).manual_seed(0)
    row = {"bandwidth": bandwidth, "training": {}}
    for batch in batches:
        model.train()

        def step(batch: int = batch) -> None:
            fixed, moving, target = synthetic_pairs(base.expand(batch, -1, -1, -1, -1), generator, PairConfig())
            output = model(fixed, moving, target, generator=generator, amp=amp)
            loss = pose_loss(output, target)["total"]
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()

        try:
            for _ in range(2):
                step()
            seconds = [_elapsed(step, device) for _ in range(steps)]
            row["training"][batch] = batch / statistics.median(seconds)
        except torch.OutOfMemoryError:
            row["training"][batch] = None
        if row["training"][batch] is None:  # out here: inside the except, its traceback still holds the step's tensors
            optimiser.zero_grad(set_to_none=True)
            torch.cuda.empty_cache()
    model.eval()
    fixed, moving, _ = synthetic_pairs(base, generator, PairConfig())
    with torch.no_grad():
        for _ in range(2):
            model(fixed, moving)
            solve(fixed, moving, bandwidth=bandwidth)
        learned = [_elapsed(lambda: model(fixed, moving), device) for _ in range(repeats)]
        plain = [_elapsed(lambda: solve(fixed, moving, bandwidth=bandwidth), device) for _ in range(repeats)]
    row.update(inference=statistics.median(learned), inference_min=min(learned), inference_max=max(learned),
               learning_free=statistics.median(plain))
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--bandwidths", nargs="+", type=int, default=[32, 64])
    parser.add_argument("--batches", nargs="+", type=count_type(), default=[32, 64])
    parser.add_argument("--steps", type=count_type(), default=10)
    parser.add_argument("--repeats", type=count_type(), default=20)
    parser.add_argument("--no-amp", dest="amp", action="store_false", help="float32 networks on CUDA")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "benchmarks" / "learned_speed.md")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    amp = args.amp and device.type == "cuda"
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU ({torch.get_num_threads()} threads)"
    rows = [measure(device, b, args.batches, args.steps, args.repeats, amp) for b in args.bandwidths]
    lines = ["| device | B | grid | " + " | ".join(f"training pairs/s, batch {b}" for b in args.batches)
             + " | inference, one pair (ms): median | min | max | learning-free solver (ms) |",
             "|---|---|---|" + "---|" * len(args.batches) + "---|---|---|---|"]
    for r in rows:
        rates = " | ".join("out of memory" if r["training"][b] is None else f"{r['training'][b]:.1f}"
                           for b in args.batches)
        lines.append(f"| {name} | {r['bandwidth']} | {2 * r['bandwidth']}^3 | {rates} | {r['inference'] * 1e3:.1f} | "
                     f"{r['inference_min'] * 1e3:.1f} | {r['inference_max'] * 1e3:.1f} | "
                     f"{r['learning_free'] * 1e3:.1f} |")
    text = (f"# Learned model speed\n\n{generated_by(__file__, argv)}, torch {torch.__version__}; UNet channels "
            f"{list(CHANNELS)}, "
            f"training {'with bfloat16 autocast for the feature extractors' if amp else 'in float32'}, inference in "
            f"float32 (as register runs); synthetic random-contrast pairs of the "
            f"MNI152 T1; training medians over {args.steps} steps, inference over {args.repeats} calls.\n\n"
            + "\n".join(lines) + "\n")
    return publish(text, args.output)


if __name__ == "__main__":
    raise SystemExit(main())
