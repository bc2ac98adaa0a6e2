"""Copies of a trained model with its rotation-stage gains scaled, to measure how far its features should outweigh the
raw volumes without training again (a pretrained model's gains are set once, by ``pretrain.feature_gain``).

Each factor writes ``MODEL_xFACTOR.safetensors`` and ``.json`` beside the model, the weights otherwise unchanged; then
``benchmarks/learned_accuracy.py --models ...`` measures them side by side.

    python benchmarks/rotation_gains.py runs/ct_mr_cpu_pretrain/model 0.25 4
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dpcn_med.models import load_model, save_model
from dpcn_med.train.pretrain import PRETRAINED_EXTRACTORS, pretrained_extractors


def positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text}: expected a factor > 0")
    return value


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path, help="a saved model (NAME, or NAME.safetensors)")
    parser.add_argument("factors", type=positive, nargs="+", help="what to multiply the rotation-stage gains by")
    args = parser.parse_args(argv)
    stem = args.model.with_suffix("") if args.model.suffix in (".safetensors", ".json") else args.model
    for factor in args.factors:
        model = load_model(stem)
        for extractor in pretrained_extractors(model).values():  # one, when the weights are shared
            extractor.gain.data *= factor
        extractors = {name: getattr(model, name) for name in PRETRAINED_EXTRACTORS}
        target = stem.with_name(f"{stem.name}_x{factor:g}")
        record = json.loads(stem.with_suffix(".json").read_text(encoding="utf-8")).get("record", {})
        save_model(model, target, record={**record, "rotation_gains_scaled_by": factor})
        print(f"{target}: gains " + ", ".join(f"{name} {e.gain.item():.4g}" for name, e in extractors.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
