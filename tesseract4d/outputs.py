"""The output-folder policy shared by every command that writes (datagen, train, export, predict,
reconstruct, evaluate, view --export, demo).

Rules:
- A command never deletes or overwrites a file it did not write. What it wrote is listed in a
  marker file (``MARKER``) inside its output folder: the command's name and its files.
- An existing, non-empty output folder is reused only when it carries the same command's
  marker; otherwise the command refuses, naming the folder and ``--overwrite``. Even with
  ``--overwrite`` only the files listed in the old marker are replaced; foreign files stay, and
  a new file that would land on a foreign one is refused.
- Results are written into a temporary sibling (``.NAME.tmp-XXXX``) and renamed into place, so
  a crash leaves the old result or the new one, never half of each; on failure only the
  staging folder is removed. A run killed outright (SIGKILL, a power cut) cannot remove it; the
  next run writing NAME names such leftovers on stderr (``note_leftovers``) and keeps them.
- An output that is, contains or lies inside one of the command's inputs is refused.
- Names taken from data (task ids, episode ids, camera names) pass ``safe_name`` before they
  become path components.
- A symbolic link anywhere below the output folder is refused (before any work and again at the
  commit), so nothing is ever written or deleted through one; the names listed in an old marker
  must stay inside the folder.
- One run at a time writes an output: a run holds its staging folder locked (``flock``, so a
  killed run's lock ends with it) until it has committed; a second run writing the same output
  refuses, naming the first one's pid, and never calls a live run's stage "killed".

Usage::

    with OutputDir(args.out, "reconstruct", inputs=[episode_path], overwrite=args.overwrite) as stage:
        write files under stage            # a Path; moved to args.out when the block succeeds
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterable

from tesseract4d.errors import UserError

MARKER = ".tesseract4d-output.json"
MARKER_VERSION = 1

# Gymnasium/ManiSkill ids ("PickCube-v1") and our own names ("base_camera", "sample_00"): letters,
# digits, "_", "-", "."; no path separators, no leading dot, so no "..".
_SAFE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,127}$")


def safe_name(value: object, field: str) -> str:
    """``value`` if it can be used as one path component, else a UserError naming ``field``."""
    if not isinstance(value, str) or not _SAFE_NAME.match(value):
        raise UserError(f"{field} {value!r} is not a valid name (letters, digits, '_', '-', '.'; no path "
                        f"separators, not starting with '.'); the file is damaged or was crafted: regenerate it")
    return value


def _resolve(path: str | os.PathLike) -> Path:
    return Path(os.path.abspath(os.path.expanduser(os.fspath(path)))).resolve()


def check_not_input(out: str | os.PathLike, inputs: Iterable[str | os.PathLike | None], flag: str = "--out") -> None:
    """Refuse an output that is, contains or lies inside one of the inputs."""
    o = _resolve(out)
    for inp in inputs:
        if inp is None:
            continue
        i = _resolve(inp)
        if o == i or o.is_relative_to(i) or i.is_relative_to(o):
            how = "is" if o == i else ("lies inside" if o.is_relative_to(i) else "contains")
            raise UserError(f"{flag} {out} {how} the input {inp}; write the output to a separate folder")


def check_writable(path: str | os.PathLike, flag: str = "--out") -> None:
    """Refuse, before any work, an output this user cannot write: an existing folder and its parent
    (a rerun writes into it and swaps it), or else the nearest existing folder above it (where it
    will be made)."""
    p = _resolve(path)
    need = [p, p.parent] if p.is_dir() else [next(q for q in p.parents if q.exists())]
    for q in need:
        if not os.access(q, os.W_OK | os.X_OK):
            raise UserError(f"{flag} {path}: {q} is not writable by this user; choose an output folder you can write, "
                            f"or change its permissions")


def read_marker(folder: Path) -> dict | None:
    try:
        d = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) and isinstance(d.get("files"), list) else None


def _write_marker(folder: Path, command: str, files: list[str]) -> None:
    tmp = folder / f".{MARKER}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps({"command": command, "version": MARKER_VERSION, "written": time.time(),
                               "files": sorted(files)}, indent=2))
    os.replace(tmp, folder / MARKER)


@contextlib.contextmanager
def signals_held():
    """Hold SIGINT and SIGTERM back while a block runs (a few renames, a file's writing) and act on
    them when it ends, so an interrupt lands before or after the block, never inside it: an output
    is the old result or the new one, a shard whole or absent. Python runs signal handlers in the
    main thread only; elsewhere this is a no-op."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.signal(s, lambda signum, frame: caught.append(signum)) for s in held}
    previous = {s: signal.SIG_DFL if h is None else h for s, h in previous.items()}  # None: set outside Python
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if caught:  # the first signal that came, handled now as it would have been then
            s = caught[0]
            if callable(previous[s]):
                previous[s](s, None)
            elif previous[s] == signal.SIG_DFL:
                os.kill(os.getpid(), s)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _as_created(path: Path, mode: int) -> Path:
    """Give a temporary file (0600) or folder (0700) the mode a plain create would (``mode`` less the
    umask), so results are as readable as the user's other files once renamed into place."""
    os.chmod(path, mode & ~_umask())
    return path


def files_as_created(path: str | os.PathLike) -> Path:
    """Give a file this command just wrote, or every file and folder under a folder it just wrote,
    the mode a plain create would: safetensors writes its files 0600, which other users of a shared
    checkpoint folder could not read."""
    root = Path(path)
    for p in [root, *root.rglob("*")] if root.is_dir() else [root]:
        if not p.is_symlink():
            _as_created(p, 0o777 if p.is_dir() else 0o666)
    return root


def _files_under(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file() or p.is_symlink())


def links_below(folder: str | os.PathLike) -> list[Path]:
    """Symbolic links anywhere below ``folder`` (not followed; ``folder`` itself is not checked)."""
    found = []
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        for name in [*dirnames, *filenames]:
            if os.path.islink(os.path.join(dirpath, name)):
                found.append(Path(dirpath) / name)
    return sorted(found)


def refuse_links_below(folder: str | os.PathLike, shown: str | os.PathLike, flag: str = "--out") -> None:
    """UserError if a symbolic link lies below ``folder``: a command writing there could replace or
    delete files elsewhere through it (``shown`` is the folder as the user named it)."""
    links = links_below(folder)
    if links:
        rel = links[0].relative_to(folder)
        raise UserError(f"{flag} {shown} holds a symbolic link, {Path(shown) / rel} -> {os.readlink(links[0])}; "
                        f"tesseract4d never writes or deletes through links below an output folder: replace it with "
                        f"a real folder or file, or choose another {flag}")


def _listed_name(name: object, folder: Path, flag: str) -> str:
    """A file name read from an old marker: relative, without '..', staying inside ``folder``."""
    if not isinstance(name, str) or not name or os.path.isabs(name) or ".." in Path(name).parts:
        raise UserError(f"{flag} {folder}: its {MARKER} lists {name!r}, which is not a file inside it; the marker is "
                        f"damaged or was crafted: move the folder away or choose another {flag}")
    return name


def _flock(path: Path) -> int | None:
    """An open descriptor of ``path`` holding an exclusive ``flock``, or None when another process
    holds one (a live run's staging folder)."""
    import fcntl

    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def _is_live_stage(path: Path) -> bool:
    """Whether a staging sibling belongs to a run still writing (it holds the folder's lock)."""
    try:
        fd = _flock(path)
    except OSError:
        return False
    if fd is None:
        return True
    os.close(fd)  # closing drops the lock we took to look
    return False


def _lock_holder(path: Path) -> str:
    """The pid holding a flock on ``path`` (Linux's /proc/locks), or 'unknown'."""
    try:
        inode = os.stat(path).st_ino
        for line in Path("/proc/locks").read_text().splitlines():
            parts = line.split()
            if len(parts) > 5 and parts[1] == "FLOCK" and parts[5].rsplit(":", 1)[-1] == str(inode):
                return parts[4]
    except (OSError, ValueError):
        pass
    return "unknown"


def note_leftovers(path: str | os.PathLike) -> list[Path]:
    """Name on stderr what killed runs writing ``path`` left beside it: staging siblings
    (``.NAME.tmp-XXXXXXXX``) and earlier results moved aside during a swap (``.NAME.old-XXXXXXXX``).
    A stage a live run holds locked (see ``OutputDir``) is not a leftover and is not named. Nothing
    is removed: a moved-aside result may be the only copy of it. Returns the leftovers."""
    target = _resolve(path)
    ours = re.compile(rf"^\.{re.escape(target.name)}\.(tmp|old)-[A-Za-z0-9_]{{8}}$")
    found = sorted((p, m.group(1)) for p in target.parent.glob(glob.escape(f".{target.name}.") + "*")
                   if (m := ours.match(p.name)) and not (m.group(1) == "tmp" and p.is_dir() and _is_live_stage(p)))
    for p, kind in found:
        if kind == "tmp":
            print(f"note: {p} is a staging {'folder' if p.is_dir() else 'file'} of a run writing {target} that was "
                  f"killed before it finished; delete it once no run is writing there", file=sys.stderr)
        elif (p / "x").exists():
            only = "" if target.exists() else f" (the only copy: move it back to {target})"
            print(f"note: {p / 'x'} is an earlier result of {target}, moved aside by a run killed while replacing "
                  f"it{only}; delete {p} when you no longer need it", file=sys.stderr)
        else:
            print(f"note: {p} is an empty folder left by a run killed while replacing {target}; delete it",
                  file=sys.stderr)
    return [p for p, _ in found]


class OutputDir:
    """Stage a command's output folder and move it into place on success (see the module doc).

    ``inputs``: paths the command reads (refused as outputs). ``overwrite``: allow writing into a
    folder that is not this command's (only this command's files are replaced).
    """

    def __init__(self, path: str | os.PathLike, command: str, *, inputs: Iterable = (), overwrite: bool = False,
                 flag: str = "--out", legacy_files: Iterable[str] = ()):
        self.path = Path(path)
        self.command = command
        self.flag = flag
        self.overwrite = overwrite
        self.stage: Path | None = None
        self.lock_fd: int | None = None
        self.legacy_files = set(legacy_files)  # the layout written before markers existed
        check_not_input(self.path, inputs, flag)
        self.previous = self._check_target()

    def _check_target(self) -> set[str]:
        """Files of an earlier run of this command that the new result replaces."""
        p = self.path
        if p.exists() and not p.is_dir():
            raise UserError(f"{self.flag} {p} is a file, not a folder; pass a folder path")
        check_writable(p, self.flag)
        if not p.exists() or not any(p.iterdir()):
            return set()
        refuse_links_below(p, self.path, self.flag)
        marker = read_marker(p)
        if marker is not None and marker.get("command") == self.command:
            return {_listed_name(f, p, self.flag) for f in marker["files"]}
        if marker is None and self.legacy_files:
            present = set(_files_under(p))
            if present and present <= self.legacy_files:
                return present
        if not self.overwrite:
            whose = f"the output of `tesseract4d {marker['command']}`" if marker else "files this command did not write"
            raise UserError(f"{self.flag} {p} already holds {whose}; choose a new or empty folder, or pass --overwrite "
                            f"to write beside them (files this command did not write are never touched)")
        return set()

    def __enter__(self) -> Path:
        target = _resolve(self.path)
        target.parent.mkdir(parents=True, exist_ok=True)
        self.stage = _as_created(Path(tempfile.mkdtemp(prefix=f".{self.path.name}.tmp-", dir=target.parent)), 0o777)
        # The run holds its stage locked until it ends (a killed run's lock ends with it): another run
        # writing the same output sees it live and refuses, instead of mixing results or calling it killed.
        self.lock_fd = _flock(self.stage)
        ours = re.compile(rf"^\.{re.escape(target.name)}\.tmp-[A-Za-z0-9_]{{8}}$")
        live = [p for p in target.parent.glob(glob.escape(f".{target.name}.tmp-") + "*")
                if p != self.stage and ours.match(p.name) and p.is_dir() and _is_live_stage(p)]
        if live:
            pid = _lock_holder(live[0])
            self._release()
            raise UserError(f"{self.flag} {self.path} is being written by another run (pid {pid}); wait for it to "
                            f"finish, or write to another {self.flag}")
        note_leftovers(self.path)
        return self.stage

    def _release(self) -> None:
        try:
            if self.stage is not None and self.stage.exists():
                shutil.rmtree(self.stage, ignore_errors=True)  # only our own staging folder
        finally:
            if self.lock_fd is not None:
                os.close(self.lock_fd)
                self.lock_fd = None

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            if exc_type is None:
                with signals_held():  # the swap of folders or files runs whole
                    self._commit()
        finally:
            self._release()
        return False

    def _commit(self) -> None:
        stage, target = self.stage, _resolve(self.path)
        if target.is_dir():  # made since the start: refused all the same
            refuse_links_below(target, self.path, self.flag)
        files_as_created(stage)
        new_files = _files_under(stage)
        if not target.exists() or not any(target.iterdir()):
            _write_marker(stage, self.command, new_files)
            if target.exists():
                target.rmdir()  # empty: nothing of anyone's is lost
            os.replace(stage, target)
            return
        existing = set(_files_under(target)) - {MARKER}
        foreign = existing - self.previous
        clash = sorted(f for f in new_files if f in foreign)
        if clash:
            raise UserError(f"{self.flag} {self.path} holds {clash[0]}, which this command did not write and would "
                            f"replace; move it away or choose another folder")
        if not foreign:
            # Everything there is ours: swap whole folders (old result or new one, never a mix).
            _write_marker(stage, self.command, new_files)
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
            os.replace(target, old / "x")
            os.replace(stage, target)
            shutil.rmtree(old, ignore_errors=True)
            return
        # Foreign files beside ours: replace our files one by one, the marker last.
        for f in sorted(self.previous - set(new_files)):
            if (target / f).is_file() or (target / f).is_symlink():  # never a folder of the user's
                (target / f).unlink()
        for f in new_files:
            (target / f).parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / f, target / f)
        _write_marker(target, self.command, new_files)


class OutputFile:
    """A single-file output (``--json``, ``--export HTML``): refuse to replace a file this command
    did not write (``is_ours(path)`` recognises its own format) unless ``overwrite``; write to a
    temporary sibling and rename."""

    def __init__(self, path: str | os.PathLike, *, inputs: Iterable = (), overwrite: bool = False,
                 flag: str = "--out", is_ours=None):
        self.path = Path(path)
        check_not_input(self.path, inputs, flag)
        if self.path.is_dir():
            raise UserError(f"{flag} {path} is a folder; pass a file name such as {self.path / 'out'}")
        if self.path.exists() and not overwrite and not (is_ours and is_ours(self.path)):
            raise UserError(f"{flag} {path} exists and was not written by this command; choose another name or "
                            f"pass --overwrite to replace it")
        self.tmp: Path | None = None

    def __enter__(self) -> Path:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        note_leftovers(self.path)
        fd, name = tempfile.mkstemp(prefix=f".{self.path.name}.tmp-", dir=self.path.parent)
        os.close(fd)
        self.tmp = _as_created(Path(name), 0o666)
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            with signals_held():
                os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)
        return False


def claim_folder(path: str | os.PathLike, command: str, *, inputs: Iterable = (), legacy_marker: str | None = None,
                 flag: str = "--out") -> bool | None:
    """For commands that write in place and resume (datagen, a training run): refuse ``path`` if
    it is a file, overlaps an input, or is a non-empty folder that is neither this command's (its
    marker, or ``legacy_marker``, a file such a folder always holds) nor empty. A new or empty
    folder gets the marker. Returns True when the folder was created now, False when it existed
    empty, None when it already held this command's output (see ``release_new_folder``)."""
    p = Path(path)
    check_not_input(p, inputs, flag)
    if p.exists() and not p.is_dir():
        raise UserError(f"{flag} {p} is a file, not a folder; pass a folder path")
    if p.exists() and any(p.iterdir()):
        marker = read_marker(p)
        ours = (marker is not None and marker.get("command") == command) or (
            marker is None and legacy_marker is not None and (p / legacy_marker).exists())
        if not ours:
            whose = f"the output of `tesseract4d {marker['command']}`" if marker else "files this command did not write"
            raise UserError(f"{flag} {p} already holds {whose}; choose a new or empty folder")
        return None
    created = not p.exists()
    p.mkdir(parents=True, exist_ok=True)
    _write_marker(p, command, [])
    return created


def release_new_folder(path: str | os.PathLike, own_files: Iterable[str] = (), remove_folder: bool = True) -> None:
    """After a failed start of a command that claimed a new or empty ``path``: remove the marker,
    the named files it wrote and every empty folder left (``path`` itself too if
    ``remove_folder``), so a mistake leaves nothing behind. Files not named are kept."""
    p = Path(path)
    for name in [MARKER, *own_files]:
        (p / name).unlink(missing_ok=True)
    if not p.is_dir():
        return
    for d in sorted((q for q in p.rglob("*") if q.is_dir()), key=lambda q: len(q.parts), reverse=True):
        try:
            d.rmdir()
        except OSError:
            pass
    if remove_folder:
        try:
            p.rmdir()
        except OSError:
            pass
