"""Carry the text encoder to another machine as a table of its outputs: every wording a training run can draw.

The MiniLM weights (90 MB) are more than a lent GPU machine's transfer limit leaves room for beside the
latent caches (``scripts/latent_cache_8bit.py``). A training run only ever encodes the instructions of its
datasets and, with ``--rephrase``, their training paraphrases (``datagen.paraphrases``): a few thousand
sentences. ``make`` encodes them here with the project's own encoder (float32) and stores each one's
token embeddings without the padding, in float16 (rounding at most about 0.002); ``run`` runs a
``tesseract4d`` command there with the encoder replaced by that table. A sentence outside the table stops
the run with its text; ``run`` checks every wording of its ``--data`` before anything trains.

  .venv/bin/python scripts/text_table.py make --out TABLE data/v2_tabletop data/v2_tasks
  python3 scripts/text_table.py run TABLE train --data DATA/v2_tabletop DATA/v2_tasks --rephrase 0.5 ...  # there
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

TABLE_FILE, META_FILE = "text_table.safetensors", "text_table.json"


def wordings(datasets: list[Path], camera: str = "close") -> list[str]:
    """Every instruction of the datasets (from their latent caches, or their episodes where they have none:
    ``distill``'s pairs read episodes) and its training paraphrases, sorted."""
    from datagen.paraphrases import train_paraphrases
    from tesseract4d import dataset_format as df
    from tesseract4d.model.latent_cache import CACHE_FILE, default_cache_dir

    texts: set[str] = set()
    for d in datasets:
        cache = default_cache_dir(d, camera) / CACHE_FILE
        if cache.is_file():
            instructions = [e["instruction"] for e in json.loads(cache.read_text())["episodes"]]
        else:
            instructions = [df.read_episode_attrs(f)["instruction"] for f in df.list_episode_files(d)]
        for instruction in instructions:
            texts.update(train_paraphrases(instruction))
    return sorted(texts)


def make(datasets: list[Path], out: Path, preset: str = "latent-128", camera: str = "close") -> Path:
    import torch
    from safetensors.torch import save_file

    from tesseract4d.model.build import build_text_encoder
    from tesseract4d.model.presets import get_preset

    texts = wordings(datasets, camera)
    encoder = build_text_encoder(get_preset(preset))
    emb = torch.cat([encoder.encode(texts[i:i + 64]) for i in range(0, len(texts), 64)])  # (n, L, d), padding zero
    used = (emb != 0).any(-1).sum(-1)  # tokens per sentence: the padding is at the end
    out.mkdir(parents=True, exist_ok=True)
    save_file({str(k): emb[k, :used[k]].half().contiguous() for k in range(len(texts))}, str(out / TABLE_FILE))
    meta = {"texts": texts, "kind": encoder.kind, "max_tokens": encoder.max_tokens, "dim": encoder.dim, "preset": preset}
    (out / META_FILE).write_text(json.dumps(meta))  # last: a table is complete when its meta file is there
    print(f"{out}: {len(texts)} sentences, {int(used.sum())} tokens")
    return out


class TableEncoder:
    """The text encoder's interface (kind, max_tokens, dim, encode) read from a table of ``make``."""

    def __init__(self, folder: Path):
        from safetensors.torch import load_file

        meta = json.loads((folder / META_FILE).read_text())
        self.kind, self.max_tokens, self.dim = meta["kind"], meta["max_tokens"], meta["dim"]
        self.index = {t: i for i, t in enumerate(meta["texts"])}
        self.tensors = load_file(str(folder / TABLE_FILE))

    def encode(self, instructions: list[str]):
        import torch

        out = torch.zeros(len(instructions), self.max_tokens, self.dim)
        for k, text in enumerate(instructions):
            if text not in self.index:
                raise SystemExit(f"{text!r} is not in the text table: make it again with the run's --data")
            e = self.tensors[str(self.index[text])].float()
            out[k, :len(e)] = e
        return out


def run(folder: Path, argv: list[str]) -> int:
    import tesseract4d.model.build as build
    from tesseract4d.cli import main

    table = TableEncoder(folder)
    if "--data" in argv:
        data = []
        for a in argv[argv.index("--data") + 1:]:
            if a.startswith("--"):
                break
            data.append(Path(a))
        missing = [t for t in wordings(data) if t not in table.index]
        if missing:
            raise SystemExit(f"{len(missing)} wordings of --data are not in the table, e.g. {missing[0]!r}")
    original = build.build_text_encoder
    build.build_text_encoder = lambda preset, pretrained_dir=None, device="cpu": table
    try:
        return main(argv)
    finally:
        build.build_text_encoder = original


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make", help="encode every wording of the datasets' latent caches")
    m.add_argument("datasets", nargs="+", type=Path)
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--camera", default="close")
    m.add_argument("--preset", default="latent-128", help="the preset whose text encoder and length to use")
    r = sub.add_parser("run", help="run a tesseract4d command with the table as its text encoder")
    r.add_argument("table", type=Path)
    r.add_argument("args", nargs=argparse.REMAINDER, help="the tesseract4d command and its options")
    args = parser.parse_args(argv)
    if args.command == "make":
        make(args.datasets, args.out, preset=args.preset, camera=args.camera)
        return 0
    return run(args.table, args.args)


if __name__ == "__main__":
    sys.exit(main())
