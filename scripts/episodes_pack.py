"""Carry episodes to another machine in a few small files: quantised, lzma-compressed, self-contained parts.

Training an autoencoder (or its decoder) needs pixels, not latents, so a GPU machine that can only
receive a few tens of MB per call needs the episodes themselves in as few bytes as they allow. This
packs episodes of one or more datasets (an even spread of ``--episodes`` of each, every
``--frame-stride``-th frame) into ``part_NN.bin`` + ``part_NN.json`` of at most ``--part-mb`` MB each;
every part holds whole episodes, so a part unpacks on its own. On the other machine ``unpack`` writes
them back as dataset folders (``info.json`` + episode files) through the project's own writer, and
refuses, before writing anything, when an episode file it would write exists already:

- depth: metres rounded to 0.1 mm (uint16; depths beyond 6.5535 m, far outside the model's
  0.2-1.5 m, are stored as 6.5535 m; 0 = no measurement stays 0);
- normals: each component rounded to 1/127 (int8; at most 0.45 degrees off, 0 stays 0);
- RGB, segmentation, cameras, actions, poses and every attribute: exact.

About 10 KB per 128x128 frame (16 frames of an episode compress together).

With ``--first-frame`` every camera's images are its first frame repeated (poses, actions and
attributes kept): all that ``tesseract4d distill`` reads of an episode for its pairs is the first
frame and the instruction, and an episode packed so takes about 60 KB at 128x128 and 16 frames.

  .venv/bin/python scripts/episodes_pack.py pack data/v2_tabletop data/v2_tasks --episodes 1000 \\
      --frame-stride 2 --out PACKED
  .venv/bin/python scripts/episodes_pack.py pack data/v2_tabletop --camera close --first-frame --out PAIRS_IN
  python3 scripts/episodes_pack.py unpack PACKED --out DATA_DIR       # on the other machine
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import lzma
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

DEPTH_STEP_M = 1e-4
NORMAL_STEP = 1.0 / 127


def _quantise(name: str, a: np.ndarray) -> tuple[np.ndarray, str | None]:
    if name == "depth_m":
        return np.clip(np.round(a / DEPTH_STEP_M), 0, 65535).astype(np.uint16), "depth"
    if name == "normal_cam":
        return np.clip(np.round(np.asarray(a, np.float32) / NORMAL_STEP), -127, 127).astype(np.int8), "normal"
    return a, None


def _restore(a: np.ndarray, how: str | None) -> np.ndarray:
    if how == "depth":
        return (a.astype(np.float64) * DEPTH_STEP_M).astype(np.float32)
    if how == "normal":
        return a.astype(np.float32) * NORMAL_STEP
    return a


def encode_episode(ep) -> bytes:
    """One episode as lzma-compressed bytes: a JSON description, then its arrays in .npy format."""
    arrays: list[bytes] = []

    def walk(value, name: str = ""):
        if dataclasses.is_dataclass(value):
            return {"__dataclass__": type(value).__name__,
                    "fields": {f.name: walk(getattr(value, f.name), f.name) for f in dataclasses.fields(value)}}
        if isinstance(value, np.ndarray):
            q, how = _quantise(name, value)
            buf = io.BytesIO()
            np.save(buf, np.ascontiguousarray(q), allow_pickle=False)
            arrays.append(buf.getvalue())
            return {"__array__": len(arrays) - 1, "how": how}
        if isinstance(value, dict):
            return {"__dict__": [[str(k), isinstance(k, int), walk(v, str(k))] for k, v in value.items()]}
        return value

    desc = json.dumps(walk(ep)).encode()
    sizes = [len(desc)] + [len(a) for a in arrays]
    head = json.dumps(sizes).encode()
    return lzma.compress(len(head).to_bytes(4, "little") + head + desc + b"".join(arrays), preset=9)


def decode_episode(blob: bytes):
    from tesseract4d import dataset_format as df

    raw = lzma.decompress(blob)
    n = int.from_bytes(raw[:4], "little")
    sizes = json.loads(raw[4:4 + n])
    pos = 4 + n
    desc = json.loads(raw[pos:pos + sizes[0]])
    pos += sizes[0]
    arrays = []
    for s in sizes[1:]:
        arrays.append(np.load(io.BytesIO(raw[pos:pos + s]), allow_pickle=False))
        pos += s
    classes = {"Episode": df.Episode, "CameraFrames": df.CameraFrames}

    def build(value):
        if isinstance(value, dict) and "__dataclass__" in value:
            return classes[value["__dataclass__"]](**{k: build(v) for k, v in value["fields"].items()})
        if isinstance(value, dict) and "__array__" in value:
            return _restore(arrays[value["__array__"]], value["how"])
        if isinstance(value, dict) and "__dict__" in value:
            return {(int(k) if is_int else k): build(v) for k, is_int, v in value["__dict__"]}
        return value

    return build(desc)


def _spread(files: list[Path], count: int | None) -> list[Path]:
    if count is None or count >= len(files):
        return files
    return [files[i] for i in np.linspace(0, len(files) - 1, count).round().astype(int)]


def first_frame_only(ep):
    """The episode with every camera's images replaced by its first frame, repeated to its length."""
    def repeat(a):
        return None if a is None else np.repeat(a[:1], len(a), axis=0)

    cameras = {name: dataclasses.replace(cam, rgb=repeat(cam.rgb), depth_m=repeat(cam.depth_m),
                                         normal_cam=repeat(cam.normal_cam), segmentation=repeat(cam.segmentation))
               for name, cam in ep.cameras.items()}
    return dataclasses.replace(ep, cameras=cameras)


def pack(datasets: list[Path], out: Path, episodes: int | None = None, frame_stride: int = 1,
         camera: str | None = None, part_mb: float = 44.0, first_frame: bool = False) -> list[Path]:
    from tqdm import tqdm

    from tesseract4d import dataset_format as df

    if out.exists() and any(out.iterdir()):
        raise SystemExit(f"{out} is not empty; pack into a new folder")
    out.mkdir(parents=True, exist_ok=True)
    infos = {d.name: json.loads((d / df.INFO_FILE).read_text()) for d in datasets}
    if len(infos) != len(datasets):
        raise SystemExit("two datasets share a folder name; unpack writes each under its name")
    todo = [(d, f) for d in datasets for f in _spread(df.list_episode_files(d), episodes)]
    parts: list[Path] = []
    records, buf = [], bytearray()

    def flush():
        if not records:
            return
        stem = out / f"part_{len(parts):02d}"
        stem.with_suffix(".bin").write_bytes(bytes(buf))
        stem.with_suffix(".json").write_text(json.dumps({"infos": infos, "episodes": records}))
        parts.append(stem.with_suffix(".bin"))
        print(f"{stem.with_suffix('.bin')}: {len(records)} episodes, {len(buf) / 1e6:.1f} MB", flush=True)
        records.clear()
        buf.clear()

    for d, f in tqdm(todo, desc="packing", unit="ep"):
        ep = df.read_episode(f, cameras=None if camera is None else [camera], frames=slice(None, None, frame_stride))
        blob = encode_episode(first_frame_only(ep) if first_frame else ep)
        if len(buf) + len(blob) > part_mb * 1e6:
            flush()
        records.append({"dataset": d.name, "file": f.relative_to(d).as_posix(), "offset": len(buf), "size": len(blob)})
        buf += blob
    flush()
    return parts


def _unpack_one(job: tuple[str, int, int, str, str]) -> str:
    from tesseract4d import dataset_format as df

    bin_path, offset, size, folder, target = job
    with open(bin_path, "rb") as f:
        f.seek(offset)
        ep = decode_episode(f.read(size))
    if df.episode_path(folder, ep.env_id, ep.seed, ep.variant) != Path(target):
        raise SystemExit(f"{bin_path}: episode {ep.episode_id} does not belong at {target}; the part is corrupt")
    df.write_episode(folder, ep, compression_level=1)
    return folder


def unpack(src: Path, out: Path, workers: int | None = None) -> list[Path]:
    from concurrent.futures import ProcessPoolExecutor

    from tesseract4d import dataset_format as df

    jobs, infos = [], {}
    for header_path in sorted(src.glob("part_*.json")):
        header = json.loads(header_path.read_text())
        infos.update(header["infos"])
        bin_path = str(header_path.with_suffix(".bin"))
        jobs += [(bin_path, r["offset"], r["size"], str(out / r["dataset"]), str(out / r["dataset"] / r["file"]))
                 for r in header["episodes"]]
    # Never replace an episode file: unpacking into a folder that holds the originals would swap them
    # for their quantised copies. Parts hold disjoint episodes, so unpacking them one by one is fine.
    taken = [job[4] for job in jobs if Path(job[4]).exists()]
    if taken:
        raise SystemExit(f"{len(taken)} episode files exist already (e.g. {taken[0]}); unpack into a new --out folder")
    for name, info in infos.items():
        df.init_dataset(out / name, df.DatasetInfo.from_dict(info))
    written: dict[str, int] = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for folder in pool.map(_unpack_one, jobs, chunksize=8):
            written[folder] = written.get(folder, 0) + 1
    for folder, n in written.items():
        print(f"{folder}: {n} episodes written")
    return [Path(folder) for folder in written]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="pack episodes of dataset folders")
    p.add_argument("datasets", nargs="+", type=Path)
    p.add_argument("--out", type=Path, required=True, help="a new folder for the parts")
    p.add_argument("--episodes", type=int, default=None, help="episodes of each dataset, evenly spread (default all)")
    p.add_argument("--frame-stride", type=int, default=1, help="keep every k-th frame (default 1)")
    p.add_argument("--first-frame", action="store_true",
                   help="every camera's images its first frame repeated (enough for `distill`'s pairs)")
    p.add_argument("--camera", default=None, help="keep only this camera (default all)")
    p.add_argument("--part-mb", type=float, default=44.0, help="largest part written, in MB (default 44)")
    u = sub.add_parser("unpack", help="write the parts back as dataset folders")
    u.add_argument("packed", type=Path)
    u.add_argument("--out", type=Path, required=True)
    u.add_argument("--workers", type=int, default=None, help="processes (default: one per CPU)")
    args = parser.parse_args(argv)
    if args.command == "pack":
        pack(args.datasets, args.out, args.episodes, args.frame_stride, args.camera, args.part_mb, args.first_frame)
    else:
        unpack(args.packed, args.out, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
