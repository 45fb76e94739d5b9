"""Closed-loop benchmark: seconds per replanning cycle (predict + reconstruct + IDM), per stage.

One cycle = one world-model prediction (16 frames from the current frame and the instruction)
plus, for each of the k clip frames executed, back-projecting the current and the predicted frame
into point clouds and one IDM forward pass. Also timed for comparison: the full 4D reconstruction
of the predicted clip (normal integration + temporal consistency + TSDF), which the loop does not
use (see the table), and rendering one observation.

  PYTHONPATH=. OMP_WAIT_POLICY=PASSIVE python benchmarks/bench_rollout.py --idm runs/idm/final \
      [--checkpoint tesseract4d/checkpoints/v2] [--draws 1] --repeats 5

Target: a cycle <= 2 s on the 2-core CPU.
"""

from __future__ import annotations

import argparse
import statistics
import time
from measure import add_isa_cap_argument, apply_isa_cap, machine_line

from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT  # no torch: the ISA cap is applied later


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--idm", required=True, help="IDM folder (train-idm RUN/final)")
    ap.add_argument("--checkpoint", default=str(SHIPPED_CHECKPOINT), help="world model (default: the shipped default, v2-2step)")
    ap.add_argument("--task", default="PushCube-v1")
    ap.add_argument("--seed", type=int, default=100000)
    ap.add_argument("--replan-every", type=int, default=4)
    ap.add_argument("--sample-steps", type=int, help="diffusion steps per prediction (default: the checkpoint's)")
    ap.add_argument("--draws", type=int, help="noise draws per prediction, the best kept (default: the checkpoint's, "
                                             "2 for the shipped models; each draw costs one prediction)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                    help="world-model precision (default %(default)s: bf16 only where the CPU has it)")
    add_isa_cap_argument(ap)
    args = ap.parse_args()
    apply_isa_cap(args.cap_isa)

    from tesseract4d import runtime

    runtime.configure()
    import numpy as np
    import torch

    from datagen.simulate import EpisodeSimulator, SimConfig
    from reconstruction.reconstruct import reconstruct_episode
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.text_encoder import TextEncoder
    from tesseract4d.policy.idm import load_idm, sentence_embeddings
    from tesseract4d.policy.loop import LoopConfig, WorldModelFuture, idm_points

    idm = load_idm(args.idm)
    pipe = load_pipeline(args.checkpoint, precision=args.precision)
    cfg = LoopConfig(replan_every=args.replan_every, sample_steps=args.sample_steps, draws=args.draws,
                     resolution=tuple(pipe.resolution), camera=pipe.camera_name or "close")
    wm = WorldModelFuture(pipe, cfg)
    sim = EpisodeSimulator(args.task, SimConfig(height=cfg.resolution[0], width=cfg.resolution[1], cameras=[cfg.camera]))
    first = sim.first_frame(args.seed)
    text = sentence_embeddings(TextEncoder("minilm", max_tokens=32), [first.instruction])
    qpos = torch.from_numpy(sim.env.unwrapped.agent.robot.get_qpos()[0].numpy().astype(np.float32))[None]
    rng = np.random.default_rng(0)
    rows = {k: [] for k in ("observe", "predict", "reconstruct", "idm", "cycle", "full_4d_reconstruction")}
    for r in range(args.repeats + 1):  # the first round warms up and is not counted
        t0 = time.perf_counter()
        frame = sim.observe()[cfg.camera]
        t1 = time.perf_counter()
        clip = wm.clip(frame, args.task, args.seed, first.instruction, r)
        t2 = time.perf_counter()
        recon = idm_s = 0.0
        for j in range(1, cfg.replan_every + 1):
            a = time.perf_counter()
            # as in the loop: frames reach the IDM at its resolution
            now = idm_points(idm.config, frame.rgb, frame.depth_m, frame.K, frame.T_world_cam, rng)
            nxt = idm_points(idm.config, clip.rgb[j], clip.depth_m[j], clip.K[j], clip.T_world_cam[j], rng)
            b = time.perf_counter()
            with torch.no_grad():
                idm.decode(idm(torch.from_numpy(now)[None], torch.from_numpy(nxt)[None], text, qpos), qpos)
            recon += b - a
            idm_s += time.perf_counter() - b
        t3 = time.perf_counter()
        reconstruct_episode(clip.episode)
        t4 = time.perf_counter()
        if r == 0:
            continue
        rows["observe"].append(t1 - t0)
        rows["predict"].append(t2 - t1)
        rows["reconstruct"].append(recon)
        rows["idm"].append(idm_s)
        rows["cycle"].append((t2 - t1) + recon + idm_s)
        rows["full_4d_reconstruction"].append(t4 - t3)
    sim.close()
    import torch

    print(machine_line(f"torch capability {torch.backends.cpu.get_cpu_capability()}"))
    draws = (clip.episode.metadata["prediction"].get("draws") or {}).get("count", 1)
    print(f"task {args.task}, k = {cfg.replan_every} clip frames per cycle, {args.sample_steps or pipe.preset.num_steps} diffusion steps, "
          f"{'the best of ' + str(draws) + ' noise draws' if draws > 1 else 'one noise draw'} per prediction, "
          f"{idm.config.num_points} points per cloud, world model {pipe.resolution[0]}x{pipe.resolution[1]}, "
          f"{'bf16' if pipe.bf16 else 'fp32'}, {args.repeats} repeats")
    print(f"{'stage':<26}{'median s':>10}{'min s':>10}")
    for k, v in rows.items():
        note = "  (not in the loop)" if k == "full_4d_reconstruction" else ("  (per observation)" if k == "observe" else "")
        print(f"{k:<26}{statistics.median(v):>10.3f}{min(v):>10.3f}{note}")


if __name__ == "__main__":
    main()
