"""Generate a dataset: fan (task, seed) attempts out over workers, keep successes, resume.

Semantics
- ``episodes`` is the number of *successful* episodes wanted per task. Seeds are tried in order
  from ``seed_start``; failed plans are skipped. ``max_attempts`` caps the seeds tried per task
  (default ``4 * episodes + 4``); a task that hits the cap is reported, not retried forever.
- Each worker simulates, renders and writes its own episode files (one shard per episode,
  written atomically by ``tesseract4d.dataset_format.write_episode``). The driver appends every
  attempt's outcome to ``DIR/datagen_attempts.jsonl``, so a rerun skips seeds that failed before
  as well as episodes already on disk. A killed run leaves at most ``*.partial.*`` files, which
  never count and are removed by the next run.
- ``workers == 1`` without a Ray address runs in this process; ``workers > 1`` starts that many
  local worker processes (no server, no open port; they end with the driver, even when it is
  killed). With ``ray_address``, Ray actors (one CPU each) on that cluster do the work: every
  node needs this package installed and ``out`` on a shared file system, and a token-authenticated
  cluster the token (docs/ray_cluster.md). An actor lost with its machine is replaced by another
  actor for its attempt; every attempt's record names the machine (``node``) that ran it. A
  local Ray instance is never started: Ray 2.60 binds its services to every interface.
- Skill mode (the project's tabletop scene always; other tasks with ``skills`` or
  ``instructions_per_scene`` > 1): a job is a counterfactual group, K = ``instructions_per_scene``
  futures of one seed's initial state (``datagen/counterfactual.py``), written as
  ``seed_<seed>_k<k>.h5``; ``episodes`` then counts groups (scenes) per task, and a seed counts as
  done once all K of its files exist. The report adds per-skill planner success rates.
- Chained episodes (``chain_skills`` = 2-4, tabletop only, ``datagen/chains.py``): a job is one
  episode of that many skills in a row with an instruction schedule, written as ``seed_<seed>.h5``.
- Outputs besides episodes: ``datagen_config.json`` (resolved config), ``datagen_report.json``
  (per-task planner success rates and throughput) and MP4 previews.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from datagen.simulate import EpisodeSimulator, SimConfig, check_vulkan_env
from datagen.tasks import get_task
from tesseract4d.dataset_format import (
    INFO_FILE, LOCK_FILE, PREVIEWS_DIR, DatasetInfo, atomic_write_text, init_dataset, list_episode_files,
    preview_path, read_episode, read_episode_attrs, remove_partial_files, write_episode,
)
from tesseract4d.configs import knob
from tesseract4d.errors import UserError
from tesseract4d.outputs import claim_folder, release_new_folder
from tesseract4d.previews import write_preview
from datagen.skills import check_group_size, parse_skill_list
from tesseract4d import runtime
from datagen.counterfactual import run_group
from datagen.chains import check_chain, run_chain
from tesseract4d.stopping import handlers_kept

CONFIG_FILE = "datagen_config.json"
REPORT_FILE = "datagen_report.json"
ATTEMPTS_FILE = "datagen_attempts.jsonl"
MAX_IMAGE_SIDE = 2048  # larger images exhaust memory long before an episode is written
# Options that change what an episode file contains: a dataset folder keeps one value of each.
_DATASET_DEFINING = ("frames", "cameras", "camera_jitter_m", "randomize_colors", "randomize_lighting",
                     "instruction_split", "goal_marker")


def skill_mode(env_id: str, instructions_per_scene: int, skills: list[str] | None) -> bool:
    """Whether ``env_id`` is generated as counterfactual groups of skills (see the module docstring)."""
    return instructions_per_scene > 1 or skills is not None or get_task(env_id).skills_only


@dataclass
class DatagenConfig:
    """Everything `tesseract4d datagen` does; written to DIR/datagen_config.json."""

    tasks: list[str]
    episodes: int
    out: Path
    sim: SimConfig = field(default_factory=SimConfig)
    seed_start: int = 0
    max_attempts: int | None = knob(None, "seeds tried per task at most (none: 4 * episodes + 4)")
    workers: int = 1
    ray_address: str | None = knob(None, "address of a running Ray cluster, HEAD:PORT (none: local worker processes when workers > 1)")
    previews: bool = knob(True, "write MP4 previews of every episode")
    instructions_per_scene: int = 1  # K futures per initial state (skill mode)
    skills: list[str] | None = None  # skill specs (datagen/skills.py); None = all that apply
    chain_skills: int = knob(0, "skills in a row per tabletop episode, 2-4 (a chained episode with one instruction "
                                "per segment, datagen/chains.py); 0 = one skill per episode")

    def skill_mode(self, env_id: str) -> bool:
        return skill_mode(env_id, self.instructions_per_scene, self.skills)

    def group_size(self, env_id: str) -> int:
        """Episode files per seed: K in skill mode, else 1 (a chained episode is one file)."""
        return self.instructions_per_scene if self.skill_mode(env_id) and not self.chain_skills else 1

    def attempts_cap(self) -> int:
        return self.max_attempts if self.max_attempts is not None else 4 * self.episodes + 4

    def validate(self) -> None:
        for t in self.tasks:
            get_task(t)
        if self.episodes < 1:
            raise UserError(f"--episodes must be at least 1, got {self.episodes}")
        if self.workers < 1:
            raise UserError(f"--workers must be at least 1, got {self.workers}")
        if self.sim.height < 16 or self.sim.width < 16 or self.sim.height % 2 or self.sim.width % 2:
            raise UserError(f"resolution {self.sim.height}x{self.sim.width}: use even sizes of at least 16 pixels")
        if max(self.sim.height, self.sim.width) > MAX_IMAGE_SIDE:
            raise UserError(f"resolution {self.sim.height}x{self.sim.width}: at most {MAX_IMAGE_SIDE} pixels per side")
        if self.sim.frames < 0 or self.sim.frames == 1:
            raise UserError(f"--frames must be 0 (all steps) or at least 2, got {self.sim.frames}")
        if self.sim.camera_jitter_m < 0:
            raise UserError(f"--camera-jitter must be >= 0 metres, got {self.sim.camera_jitter_m}")
        if self.seed_start < 0 or self.seed_start + self.attempts_cap() > 2**32:
            raise UserError(f"--seed-start must be a seed >= 0 with room for {self.attempts_cap()} attempts below 2**32, "
                            f"got {self.seed_start}")
        if self.instructions_per_scene < 1:
            raise UserError(f"--instructions-per-scene must be at least 1 (1: one instruction per scene), "
                            f"got {self.instructions_per_scene}")
        if self.attempts_cap() < self.episodes:
            raise UserError(f"--max-attempts ({self.attempts_cap()}) must be at least --episodes ({self.episodes})")
        if self.chain_skills:
            if self.instructions_per_scene != 1:
                raise UserError("chained episodes (chain_skills) are one future per scene; drop --instructions-per-scene")
            check_chain(self.chain_skills, self.tasks, self.sim.frames, self.skills)
            return
        skill_tasks = [t for t in self.tasks if self.skill_mode(t)]
        if skill_tasks:
            parse_skill_list(",".join(self.skills) if self.skills is not None else None, skill_tasks)
            check_group_size(self.instructions_per_scene, skill_tasks, self.skills)

    def to_json(self) -> str:
        d = dataclasses.asdict(self)
        d["out"] = str(self.out)
        d["max_attempts_resolved"] = self.attempts_cap()
        return json.dumps(d, indent=2, sort_keys=True)


# --------------------------------------------------------------------------- worker


class Worker:
    """Runs attempts in one process: keeps one task's env alive, writes episodes and previews."""

    def __init__(self, out: str, sim: dict, previews: bool, render_threads: int | None = None,
                 instructions_per_scene: int = 1, skills: list[str] | None = None, chain_skills: int = 0):
        runtime.configure()
        if render_threads:  # lavapipe's rasteriser threads; one per worker avoids oversubscription
            os.environ.setdefault("LP_NUM_THREADS", str(render_threads))
        import logging

        logging.getLogger("mani_skill").setLevel(logging.ERROR)
        self.out = out
        self.sim_config = SimConfig(**sim)
        self.previews = previews
        self.instructions_per_scene = instructions_per_scene
        self.skills = skills
        self.chain_skills = chain_skills
        self._sim = None

    def attempt(self, env_id: str, seed: int) -> dict:
        """Try (env_id, seed). Returns the outcome as a JSON-able dict (no frames)."""
        import warnings

        import torch

        torch.set_num_threads(1)  # ManiSkill's tensors are tiny; threads only contend
        if self._sim is None or self._sim.env_id != env_id:
            if self._sim is not None:
                self._sim.close()
            self._sim = EpisodeSimulator(env_id, self.sim_config)
        group = skill_mode(env_id, self.instructions_per_scene, self.skills)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if self.chain_skills:
                result = run_chain(self._sim, seed, self.chain_skills, self.skills)
                episodes = result.episodes
            elif group:
                result = run_group(self._sim, seed, self.instructions_per_scene, self.skills)
                episodes = result.episodes
            else:
                result = self._sim.run(seed)
                episodes = [result.episode] if result.success else []
        t0 = time.perf_counter()
        for episode in episodes:
            write_episode(self.out, episode)
            if self.previews:
                write_preview(self.out, episode)
        write_s = time.perf_counter() - t0 if episodes else 0.0
        out = {f.name: getattr(result, f.name) for f in dataclasses.fields(result) if f.name not in ("episode", "episodes")}
        out["write_s"] = write_s
        out["instruction"] = " | ".join(e.instruction for e in episodes)
        return out

    def close(self) -> None:
        if self._sim is not None:
            self._sim.close()
            self._sim = None

    def node_address(self) -> str:
        """The address of the machine this worker runs on, as its Ray cluster knows it (Ray workers only)."""
        import ray  # imported lazily: only the Ray path has it loaded

        return ray.util.get_node_ip_address()


class _LocalPool:
    """One in-process worker: submit() runs the attempt right away."""

    def __init__(self, cfg: DatagenConfig):
        self.worker = Worker(str(cfg.out), dataclasses.asdict(cfg.sim), cfg.previews,
                             instructions_per_scene=cfg.instructions_per_scene, skills=cfg.skills,
                             chain_skills=cfg.chain_skills)
        self.capacity = 1
        self._done: list[tuple[object, dict]] = []

    def submit(self, key, env_id: str, seed: int) -> None:
        self._done.append((key, self.worker.attempt(env_id, seed)))

    def wait_one(self) -> tuple[object, dict]:
        return self._done.pop(0)

    def shutdown(self) -> None:
        self.worker.close()


def _worker_process(conn, parent_pid: int, out: str, sim: dict, previews: bool, render_threads: int,
                    instructions_per_scene: int, skills: list[str] | None, chain_skills: int = 0) -> None:
    """Main of one local worker process: attempts in, outcomes out, over ``conn`` until None."""
    import signal
    import traceback

    _die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the driver decides
    worker = Worker(out, sim, previews, render_threads, instructions_per_scene, skills, chain_skills)
    try:
        while (job := conn.recv()) is not None:
            try:
                conn.send(("ok", worker.attempt(*job)))
            except UserError as e:
                conn.send(("user_error", str(e)))
            except Exception as e:  # reported by the driver with this traceback
                conn.send(("error", f"{type(e).__name__}: {e}\n{traceback.format_exc()}"))
    except (EOFError, OSError):
        pass  # the driver is gone
    finally:
        worker.close()


def _die_with_parent(parent_pid: int) -> None:
    """Ask Linux to end this process when the process that started it ends, even by SIGKILL
    (PR_SET_PDEATHSIG); elsewhere nothing (the pipe's EOF still ends an idle worker)."""
    import ctypes
    import signal

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent_pid:  # the parent ended before the request took effect
        os._exit(1)


class _ProcessPool:
    """``workers`` local processes of this machine (no server, no port: nothing listens), each
    keeping its env alive between attempts. They end with the driver, even when it is killed."""

    def __init__(self, cfg: DatagenConfig):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")  # a fresh interpreter: no state (threads, renderer) inherited
        threads = max(1, (os.cpu_count() or 1) // cfg.workers)
        self.procs, self.conns, self.free = [], [], []
        self.pending: dict = {}  # conn -> key
        for _ in range(cfg.workers):
            here, there = ctx.Pipe()
            proc = ctx.Process(target=_worker_process, name="datagen-worker", daemon=True,
                               args=(there, os.getpid(), str(cfg.out), dataclasses.asdict(cfg.sim), cfg.previews,
                                     threads, cfg.instructions_per_scene, cfg.skills, cfg.chain_skills))
            proc.start()
            there.close()
            self.procs.append(proc)
            self.conns.append(here)
            self.free.append(here)
        self.capacity = cfg.workers

    def submit(self, key, env_id: str, seed: int) -> None:
        conn = self.free.pop()
        conn.send((env_id, seed))
        self.pending[conn] = key

    def wait_one(self) -> tuple[object, dict]:
        from multiprocessing.connection import wait

        busy = list(self.pending)
        sentinels = {self.procs[self.conns.index(c)].sentinel: c for c in busy}
        ready = wait(busy + list(sentinels))
        conn = next((r for r in ready if r in self.pending), None)
        try:
            kind, value = conn.recv() if conn is not None else (None, None)
        except (EOFError, OSError):
            kind = None
        if kind is None:  # a worker process died mid-attempt (killed, out of memory)
            dead = conn or sentinels[next(r for r in ready if r in sentinels)]
            code = self.procs[self.conns.index(dead)].exitcode
            raise UserError(f"a datagen worker process ended unexpectedly (exit status {code}) while simulating "
                            f"{self.pending[dead]}; finished episodes are kept: rerun the same command to resume")
        key = self.pending.pop(conn)
        self.free.append(conn)
        if kind == "user_error":
            raise UserError(value)
        if kind == "error":
            raise RuntimeError(f"datagen worker failed on {key}: {value}")
        return key, value

    def shutdown(self) -> None:
        for conn, proc in zip(self.conns, self.procs):
            if conn not in self.pending and proc.is_alive():
                try:
                    conn.send(None)  # idle: close its env and leave
                except OSError:
                    pass
            else:
                proc.terminate()  # mid-attempt (an error or a stop): a shard being written is finished first
        for proc in self.procs:
            proc.join(timeout=30)
            if proc.is_alive():
                proc.kill()
                proc.join()
        for conn in self.conns:
            conn.close()


class _RayPool:
    """One Ray actor per worker (one CPU each) on the cluster at ``cfg.ray_address``; attempts go
    to whichever actor is free. An actor lost with its machine is dropped and its attempt given to
    another; with none left the run stops (rerunning the command resumes)."""

    def __init__(self, cfg: DatagenConfig):
        import ray

        self.ray = ray
        if not ray.is_initialized():
            # ray.init() installs its own SIGTERM handler: the command line's stays (SIGTERM ends datagen with 143).
            with handlers_kept():
                ray.init(address=cfg.ray_address, log_to_driver=False)
        actor_cls = ray.remote(num_cpus=1, max_restarts=0)(Worker)
        self.actors = [actor_cls.remote(str(cfg.out), dataclasses.asdict(cfg.sim), cfg.previews, 1,
                                        cfg.instructions_per_scene, cfg.skills, cfg.chain_skills)
                       for _ in range(cfg.workers)]
        self.free = list(self.actors)
        self.capacity = len(self.actors)
        self.pending: dict = {}  # ObjectRef -> (key, actor, job)
        self.retry: list = []  # (key, job) whose actor was lost
        self.nodes: dict = {}  # actor -> the address of the machine it runs on

    def submit(self, key, env_id: str, seed: int) -> None:
        actor = self.free.pop()
        self.pending[actor.attempt.remote(env_id, seed)] = (key, actor, (env_id, seed))

    def wait_one(self) -> tuple[object, dict]:
        while True:
            while self.retry and self.free:
                key, job = self.retry.pop(0)
                self.submit(key, *job)
            if not self.pending:
                raise UserError(f"every Ray worker of the cluster was lost ({len(self.actors)} started); finished "
                                f"episodes are kept: check the cluster (`ray status`) and rerun the same command to "
                                f"resume")
            ready, _ = self.ray.wait(list(self.pending), num_returns=1)
            key, actor, job = self.pending.pop(ready[0])
            try:
                result = self.ray.get(ready[0])
            except self.ray.exceptions.RayTaskError as e:
                self.free.append(actor)
                cause = getattr(e, "cause", None)
                if isinstance(cause, UserError):
                    raise UserError(str(cause)) from e
                raise
            except self.ray.exceptions.RayActorError:  # its machine or process is gone: another one redoes it
                print(f"note: a Ray worker was lost while simulating {key[0]} seed {key[1]}; giving it to another "
                      f"worker", file=sys.stderr)
                self.actors.remove(actor)
                self.capacity = max(1, len(self.actors))
                self.retry.append((key, job))
                continue
            self.free.append(actor)
            result["node"] = self._node(actor)
            return key, result

    def _node(self, actor) -> str | None:
        if actor not in self.nodes:
            try:
                self.nodes[actor] = self.ray.get(actor.node_address.remote(), timeout=30)
            except Exception:  # lost since: the record goes without it
                return None
        return self.nodes[actor]

    def shutdown(self) -> None:
        for a in self.actors:
            try:
                self.ray.get(a.close.remote(), timeout=30)
            except Exception:  # a dead actor has nothing left to close
                pass
        self.ray.shutdown()


def check_ray_cluster(address: str, timeout_s: float = 5.0) -> None:
    """One-line UserErrors, before ray.init() retries for 20 s, when the cluster at ``address``
    (HOST:PORT of the head's GCS) does not answer or wants an authentication token we lack."""
    import socket

    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise UserError(f"--set ray_address={address!r}: give the head's HOST:PORT as printed by `ray start --head` "
                        f"(e.g. 10.0.0.5:6379)")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise UserError(f"no Ray cluster answers at {address} ({e.strerror or e}); start one on the head machine with "
                        f"`ray start --head --port {port}` (see docs/ray_cluster.md) or fix "
                        f"--set ray_address=HEAD:PORT") from None
    try:
        from ray._raylet import GcsClient  # the first call ray.init() makes; fails fast on a bad token
        from ray.exceptions import AuthenticationError
    except ImportError:
        return  # another Ray version: ray.init() reports on its own
    try:  # as ray.init() will: with RAY_AUTH_MODE unset, a token in ~/.ray/auth_token turns token mode on
        import logging

        from ray._private.authentication import authentication_token_setup as setup

        quiet = logging.getLogger(setup.__name__)
        level, quiet.level = quiet.level, logging.ERROR  # its notice would be a second line; ray.init() repeats it
        try:
            setup.maybe_enable_token_auth_if_token_available(warn_if_disabled=False)
        finally:
            quiet.setLevel(level)
    except ImportError:
        pass
    with_token = os.environ.get("RAY_AUTH_MODE", "").lower() == "token"
    saved_stderr, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)  # Ray's C++ client logs the refusal itself; our error below says it with the fix
    try:
        GcsClient(address=f"{host}:{port}")
    except AuthenticationError:
        if with_token:
            raise UserError(f"the Ray cluster at {address} refused this shell's authentication token (RAY_AUTH_TOKEN, "
                            f"RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token): use the head's token (print it on the head "
                            f"with `ray get-auth-token`), then rerun") from None
        raise UserError(f"the Ray cluster at {address} requires an authentication token: export RAY_AUTH_MODE=token "
                        f"and RAY_AUTH_TOKEN=<the token> (print it on the head with `ray get-auth-token`), then rerun"
                        ) from None
    finally:
        os.dup2(saved_stderr, 2)
        os.close(saved_stderr)
        os.close(devnull)
    if not with_token:  # it answered a client that sent no token: it asks for none
        print(f"warning: the Ray cluster at {address} does not ask for an authentication token, so anyone who can "
              f"reach it can run code on its machines; start its nodes with RAY_AUTH_MODE=token and a token "
              f"(docs/ray_cluster.md)", file=sys.stderr)


# --------------------------------------------------------------------------- bookkeeping


def read_attempts(root: str | os.PathLike) -> list[dict]:
    """Outcomes logged by earlier runs (a line cut off by a kill is ignored)."""
    path = Path(root) / ATTEMPTS_FILE
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def _append_attempt(root: Path, record: dict) -> None:
    with open(root / ATTEMPTS_FILE, "a") as f:
        f.write(json.dumps(record, sort_keys=True) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _remove_partial_previews(root: Path) -> None:
    base = root / PREVIEWS_DIR
    if base.is_dir():
        for p in base.glob("*/.*.partial.mp4"):
            p.unlink(missing_ok=True)


def _existing_seeds(root: Path, env_id: str, group_size: int = 1) -> set[int]:
    """Seeds of ``env_id`` with all ``group_size`` episode files on disk (seed_S.h5 or seed_S_kK.h5)."""
    counts = Counter(int(p.stem.split("_")[1]) for p in list_episode_files(root) if p.parent.name == env_id)
    return {seed for seed, n in counts.items() if n >= group_size}


def open_dataset(cfg: DatagenConfig) -> DatasetInfo:
    """Create or reopen cfg.out; refuse a folder written with different episode-defining options."""
    defining = {k: getattr(cfg.sim, k) for k in _DATASET_DEFINING}
    defining.update(instructions_per_scene=cfg.instructions_per_scene, skills=cfg.skills)
    if cfg.chain_skills:  # only chained folders name it, so folders written before it existed still resume
        defining["chain_skills"] = cfg.chain_skills
    info = DatasetInfo(fps=20.0, height=cfg.sim.height, width=cfg.sim.width, cameras=list(cfg.sim.cameras),
                       extra={"datagen": defining})
    on_disk = init_dataset(cfg.out, info)
    previous = on_disk.extra.get("datagen")
    if previous is not None and previous != defining:
        diff = {k: (previous.get(k), defining[k]) for k in defining if previous.get(k) != defining[k]}
        raise UserError(
            f"{cfg.out} was generated with other options (on disk vs requested: {diff}). "
            f"Rerun with the same options to resume it, or choose a new --out folder."
        )
    return on_disk


def summarize_skills(root: Path) -> dict:
    """Per skill variant: tries, successes and planner success rate over every logged group."""
    latest = {}
    for r in read_attempts(root):
        if "tries" in r:
            latest[(r["env_id"], r["seed"])] = r  # the latest run of a group counts
    stats: dict[str, dict] = {}
    for r in latest.values():
        for t in r["tries"]:
            s = stats.setdefault(t["variant"], {"tries": 0, "successes": 0})
            s["tries"] += 1
            s["successes"] += int(bool(t["success"]))
    for s in stats.values():
        s["success_rate"] = round(s["successes"] / s["tries"], 4)
    return dict(sorted(stats.items()))


def summarize(root: Path, tasks: list[str], group_sizes: dict[str, int] | None = None) -> dict:
    """Per-task planner statistics over every run logged in ``root`` (a group counts as one attempt)."""
    attempts = read_attempts(root)
    report = {}
    for env_id in tasks:
        recs = {}
        for r in attempts:
            if r["env_id"] == env_id:
                recs[r["seed"]] = r  # the latest outcome of a seed counts
        on_disk = _existing_seeds(root, env_id, (group_sizes or {}).get(env_id, 1))
        n_attempts = len(set(recs) | on_disk)
        n_success = len(on_disk)
        errors = Counter(r.get("error") or "ok" for r in recs.values() if not r["success"])
        steps = [r["num_steps"] for r in recs.values() if r["success"]]
        report[env_id] = {
            "attempts": n_attempts,
            "successes": n_success,
            "failures": n_attempts - n_success,
            "success_rate": round(n_success / n_attempts, 4) if n_attempts else None,
            "failure_reasons": dict(errors),
            "mean_sim_steps": round(sum(steps) / len(steps), 1) if steps else None,
        }
    return report


# --------------------------------------------------------------------------- driver


class DatasetLock:
    """``DIR/.datagen.lock`` holding the writer's pid: a second datagen on the same folder refuses;
    a lock left by a process that no longer runs (killed) is taken over with a message."""

    def __init__(self, root: Path):
        self.path = Path(root) / LOCK_FILE

    def __enter__(self) -> "DatasetLock":
        while True:
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                try:
                    pid = int(self.path.read_text().split()[0])
                except (OSError, ValueError, IndexError):
                    pid = None  # being written right now, or damaged
                if pid is not None and _pid_alive(pid):
                    raise UserError(f"{self.path.parent} is being written by another datagen (pid {pid}); wait for it "
                                    f"to finish or stop it, or write to another --out folder") from None
                if pid is None and time.time() - self.path.stat().st_mtime < 5:
                    time.sleep(0.2)
                    continue
                print(f"note: {self.path.parent} was locked by datagen pid {pid}, which no longer runs; taking over")
                self.path.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as f:
                f.write(f"{os.getpid()}\n")
            return self

    def __exit__(self, *exc) -> None:
        self.path.unlink(missing_ok=True)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def run_datagen(cfg: DatagenConfig, progress: bool = True) -> dict:
    """Generate until every task has ``cfg.episodes`` successes (or hits its attempt cap).

    Returns the report that is also written to ``DIR/datagen_report.json``. The folder must be
    new, empty or a dataset (tesseract4d.outputs); one datagen at a time writes it (DatasetLock).
    """
    cfg.validate()
    if cfg.ray_address:
        check_ray_cluster(cfg.ray_address)
    root = Path(cfg.out)
    fresh = claim_folder(root, "datagen", legacy_marker=INFO_FILE)
    with DatasetLock(root):
        try:
            check_vulkan_env()
            open_dataset(cfg)
        except BaseException:
            if fresh is not None:  # a refused start leaves nothing behind
                release_new_folder(root, [INFO_FILE, LOCK_FILE], remove_folder=fresh)
            raise
        return _generate(cfg, progress)


def _generate(cfg: DatagenConfig, progress: bool) -> dict:
    """The generation loop of :func:`run_datagen`, in the claimed, locked and opened folder."""
    from tqdm import tqdm

    root = _prepare_output(cfg)
    cap = cfg.attempts_cap()
    tried, successes = _seeds_done(cfg, root)
    sizes = {t: cfg.group_size(t) for t in cfg.tasks}
    next_seed = {t: cfg.seed_start for t in cfg.tasks}
    in_flight = Counter()

    def next_job():
        for t in cfg.tasks:
            if successes[t] + in_flight[t] >= cfg.episodes or len(tried[t]) + in_flight[t] >= cap:
                continue
            s = next_seed[t]
            while s in tried[t]:
                s += 1
            next_seed[t] = s + 1
            return t, s
        return None

    total = cfg.episodes * len(cfg.tasks)
    done_before = sum(min(successes[t], cfg.episodes) for t in cfg.tasks)
    bar = tqdm(total=total, initial=done_before, desc="datagen", unit="ep", disable=not progress, dynamic_ncols=True)
    run_attempts = run_successes = run_frames = run_episodes = 0
    t_start = time.perf_counter()
    pool = _RayPool(cfg) if cfg.ray_address else _ProcessPool(cfg) if cfg.workers > 1 else _LocalPool(cfg)
    try:
        while True:
            while sum(in_flight.values()) < pool.capacity and (job := next_job()) is not None:
                in_flight[job[0]] += 1
                pool.submit(job, *job)
            if sum(in_flight.values()) == 0:
                break
            (env_id, seed), res = pool.wait_one()
            in_flight[env_id] -= 1
            tried[env_id].add(seed)
            record = {k: res[k] for k in ("env_id", "seed", "success", "num_steps", "num_frames", "error",
                                          "plan_s", "render_s", "write_s")}
            record["time"] = time.time()
            if res.get("node"):
                record["node"] = res["node"]
            if "tries" in res:
                record["tries"] = res["tries"]
            _append_attempt(root, record)
            run_attempts += 1
            if res["success"]:
                successes[env_id] += 1
                run_successes += 1
                run_frames += res["num_frames"]
                run_episodes += sizes[env_id]
                bar.update(1)
            elapsed = max(time.perf_counter() - t_start, 1e-9)
            bar.set_postfix_str(
                f"{env_id} ok {run_successes}/{run_attempts} ({run_successes / run_attempts:.0%}) "
                f"{run_frames / elapsed:.1f} frames/s"
            )
    finally:
        bar.close()
        pool.shutdown()
    wall = time.perf_counter() - t_start
    this_run = {"attempts": run_attempts, "episodes_written": run_episodes, "groups_written": run_successes,
                "frames_rendered": run_frames, "wall_seconds": round(wall, 2),
                "frames_per_second": round(run_frames / wall, 2) if wall > 0 else None, "workers": cfg.workers}
    return _write_report(cfg, root, this_run)


def _prepare_output(cfg: DatagenConfig) -> Path:
    """Clear what a killed run left half-written in the (opened) dataset folder; save the config."""
    root = Path(cfg.out)
    remove_partial_files(root)
    _remove_partial_previews(root)
    if cfg.previews:
        _write_missing_previews(root)
    atomic_write_text(root / CONFIG_FILE, cfg.to_json())
    return root


def _write_missing_previews(root: Path) -> list[Path]:
    """The MP4 previews of episodes on disk whose preview an interrupted run did not finish."""
    written = []
    for path in list_episode_files(root):
        attrs = read_episode_attrs(path)
        if not preview_path(root, attrs["env_id"], attrs["seed"], attrs["variant"]).is_file():
            written.append(write_preview(root, read_episode(path)))
    return written


def _seeds_done(cfg: DatagenConfig, root: Path) -> tuple[dict[str, set[int]], dict[str, int]]:
    """Per task, the seeds not to try again (failed before, or written whole) and the successes on
    disk; in skill mode a seed is written once all of its group's files exist."""
    tried: dict[str, set[int]] = {t: set() for t in cfg.tasks}
    for r in read_attempts(root):  # failed seeds are not retried; a logged success whose file is gone is redone
        if r["env_id"] in tried and not r["success"]:
            tried[r["env_id"]].add(int(r["seed"]))
    written = {t: _existing_seeds(root, t, cfg.group_size(t)) for t in cfg.tasks}
    for t in cfg.tasks:
        tried[t] |= written[t]
    return tried, {t: len(written[t]) for t in cfg.tasks}


def _write_report(cfg: DatagenConfig, root: Path, this_run: dict) -> dict:
    """The report of the dataset and of this run, written to ``DIR/datagen_report.json``."""
    tasks_report = summarize(root, cfg.tasks, {t: cfg.group_size(t) for t in cfg.tasks})
    for t in cfg.tasks:
        tasks_report[t]["complete"] = tasks_report[t]["successes"] >= cfg.episodes
    report = {
        "tasks": tasks_report,
        "skills": summarize_skills(root),
        "instructions_per_scene": cfg.instructions_per_scene,
        "this_run": this_run,
        "episodes_wanted_per_task": cfg.episodes,
        "max_attempts_per_task": cfg.attempts_cap(),
    }
    atomic_write_text(root / REPORT_FILE, json.dumps(report, indent=2, sort_keys=True))
    return report


def format_report(report: dict) -> str:
    """The per-task table printed at the end of a run."""
    lines = [f"{'task':<22} {'ok':>5} {'tried':>6} {'planner success':>16}  failure reasons"]
    for env_id, r in report["tasks"].items():
        rate = "-" if r["success_rate"] is None else f"{100 * r['success_rate']:.0f} %"
        reasons = ", ".join(f"{k}: {v}" for k, v in r["failure_reasons"].items()) or "-"
        flag = "" if r.get("complete", True) else "  (attempt cap reached)"
        lines.append(f"{env_id:<22} {r['successes']:>5} {r['attempts']:>6} {rate:>16}  {reasons}{flag}")
    if report.get("skills"):
        lines.append(f"{'skill':<22} {'ok':>5} {'tried':>6} {'planner success':>16}")
        for name, r in report["skills"].items():
            lines.append(f"{name:<22} {r['successes']:>5} {r['tries']:>6} {100 * r['success_rate']:>14.0f} %")
    run = report["this_run"]
    lines.append(f"this run: {run['episodes_written']} episodes from {run['attempts']} attempts in "
                 f"{run['wall_seconds']:.1f} s, {run['frames_rendered']} frames ({run['frames_per_second']} frames/s)")
    return "\n".join(lines)
