"""The ceiling per situation of one or more autoencoders on held-out sets (tesseract4d/evaluation/ceiling.py).

Each episode's truth is encoded and decoded by every autoencoder given (a first-frame decoder is handed the
truth's frame 0), and permanence and the moved object's "found whole" are counted per skill and per
situation (in the gripper, occluded by the arm, moving), beside the truth itself. Writes OUT/ceiling.json
and OUT/ceiling.md; with --strips also a PNG per listed episode: truth, then each autoencoder, frames
across.

  python benchmarks/measure_ceiling.py --autoencoder old=tesseract4d/checkpoints/v2/autoencoder \\
      --autoencoder new=runs/ff_concat/autoencoder --data data/heldout_tabletop data/heldout_cubes \\
      --out outputs/ceiling --strips Tesseract4dTabletop-v1/seed_100000_k1
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def strip(rows: list, frames: list[int]):
    """(rows x frames) grid of (T, H, W, 3) uint8 clips, 2 px gaps: (H', W', 3) uint8."""
    import numpy as np

    H, W = rows[0].shape[1:3]
    out = np.full((len(rows) * (H + 2), len(frames) * (W + 2), 3), 255, np.uint8)
    for i, clip in enumerate(rows):
        for j, t in enumerate(frames):
            out[i * (H + 2):i * (H + 2) + H, j * (W + 2):j * (W + 2) + W] = clip[t]
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--autoencoder", action="append", required=True, help="NAME=FOLDER (repeatable)")
    p.add_argument("--data", type=Path, nargs="+", required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--bf16", action="store_true", help="decode in bf16 autocast (as the pipeline on a CPU with native bf16)")
    p.add_argument("--strips", nargs="*", default=[], help="episode ids (ENV/seed_S_kK) to draw")
    p.add_argument("--upscale", type=int, default=2, help="pixel repeat of the strips")
    a = p.parse_args()
    import numpy as np

    from tesseract4d import dataset_format as df
    from tesseract4d.evaluation.ceiling import ceiling_report, report_markdown, round_trip
    from tesseract4d.model.autoencoder_loading import load_autoencoder

    aes = dict(s.split("=", 1) for s in a.autoencoder)
    a.out.mkdir(parents=True, exist_ok=True)
    report = ceiling_report(aes, a.data, bf16=a.bf16, log=lambda m: print(m, flush=True))
    report["bf16"] = a.bf16
    (a.out / "ceiling.json").write_text(json.dumps(report, indent=2))
    (a.out / "ceiling.md").write_text(report_markdown(report))
    print(report_markdown(report))
    if a.strips:
        import imageio.v3 as iio

        models = {n: load_autoencoder(f) for n, f in aes.items()}
        for path in [f for folder in a.data for f in df.list_episode_files(folder)]:
            gt = df.read_episode(path)
            if gt.episode_id not in a.strips:
                continue
            cam = next(iter(gt.cameras))
            clips = [gt.cameras[cam].rgb] + [round_trip(m, gt, cam, bf16=a.bf16) for m in models.values()]
            T = len(clips[0])
            img = strip(clips, list(range(0, T, max(1, T // 6)))[:6] + [T - 1])
            img = np.repeat(np.repeat(img, a.upscale, 0), a.upscale, 1)
            name = gt.episode_id.replace("/", "_") + ".png"
            iio.imwrite(a.out / name, img)
            print(f"strip: {a.out / name} (rows: truth, {', '.join(models)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
