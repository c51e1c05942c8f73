"""The content-addressed artifact store.

Layout under the store root (default ``artifacts/``)::

    objects/ab/<id>/...        one directory per artifact, named by its content id, read-only
    manifests/ab/<id>.json     its file list and file hashes (for checks and ``verify``)
    runcache/ab/<key>.json     stage-run records: run key -> output artifact ids + provenance
    runs/<subject>/            per-run views: <stage>/<output> links into objects/, the lockfile, logs
    tmp/                       staging: <label>-pid<PID>.<host>.<random>/ per writer (see below)
    quarantine/                corrupt objects moved aside by ``verify`` (nothing is deleted silently)
    locks/                     file locks
    hashes.db                  the stat cache (see :mod:`humanvdm_core.workflow.hashing`)

Contracts:
- An object directory appears under its final name only complete (staged in tmp/, then renamed), so
  a killed stage never leaves anything in objects/ that looks complete.
- ``has(id)`` (every cache lookup: each stage run's outputs, each run input) checks an object
  without re-reading it: its file list must equal its manifest, and each file's hash comes from the
  stat cache, which trusts a stored hash only while the file's inode, size, mtime and ctime are
  unchanged AND its first and last 64 KiB (the whole file up to 128 KiB) hash as when it was
  hashed; anything else re-reads the file. So a file changed through the file system (even with
  its size and mtime put back) is never a cache hit, nor is damage in a file's first or last
  64 KiB; damage beneath the file system to the middle of a larger file is found only by
  ``verify``, which re-reads every byte and quarantines what fails. Details: :mod:`humanvdm_core.workflow.hashing`.
- Processes on one machine sharing a store coordinate with file locks: one per stage-run key (the
  second process waits, then finds the first one's result) and a store lock that ``gc`` takes
  exclusively. Across machines (a store on NFS, the Ray executor) nothing relies on these locks:
  one driver commits, and a commit is a rename, atomic on any POSIX file system.
- Staging folders are named for their writer (``pid<PID>.<host>``): a run removes the ones of
  dead processes of its own host when it starts (:meth:`clean_stale_staging`), so a killed run's
  partial outputs go at the next run; ``gc`` removes every leftover.
- A full disk (ENOSPC/EDQUOT) while committing raises :class:`~humanvdm_core.workflow.errors.DiskFullError`
  (one line: where, and how much to free) and leaves nothing half-written: the staged files are
  removed and no record is written.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import shutil
import socket
import tempfile
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from filelock import FileLock

from humanvdm_core.workflow.atomic import atomic_write_text
from humanvdm_core.workflow.errors import DiskFullError, HumanVDMError, is_disk_full
from humanvdm_core.workflow.hashing import StatCache, hash_tree, list_files, tree_id


class StoreInUseError(HumanVDMError, RuntimeError):
    """The store is held by a running pipeline (``gc`` refuses: exit 2 with this message, no traceback)."""


@dataclass
class VerifyReport:
    checked: int
    corrupt: list[str]
    quarantined: list[str]


def _shard(name: str) -> str:
    return f"{name[:2]}/{name}"


HOST = re.sub(r"[^A-Za-z0-9-]", "_", socket.gethostname()) or "host"
_STAGING_OWNER = re.compile(r"-pid(\d+)\.([A-Za-z0-9_-]+)\.[^.]*$")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def tree_size(path: str | os.PathLike) -> int:
    """Bytes in the regular files under ``path`` (0 when it is gone)."""
    total = 0
    for dirpath, _, filenames in os.walk(path):
        for name in filenames:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(dirpath, name)).st_size
    return total


class Store:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()
        for sub in ("objects", "manifests", "runcache", "runs", "tmp", "locks", "quarantine"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self.stat_cache = StatCache(self.root / "hashes.db")

    # ------------------------------------------------------------------ objects

    def object_path(self, artifact_id: str) -> Path:
        return self.root / "objects" / _shard(artifact_id)

    def _manifest_path(self, artifact_id: str) -> Path:
        return self.root / "manifests" / f"{_shard(artifact_id)}.json"

    def manifest(self, artifact_id: str) -> dict[str, str] | None:
        try:
            data = json.loads(self._manifest_path(artifact_id).read_text())
            return dict(data["files"])
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def has(self, artifact_id: str) -> bool:
        """True when the object is present and its files match its manifest (stat-cached hashes)."""
        return self._check(artifact_id, trust_cache=True)

    def _check(self, artifact_id: str, trust_cache: bool) -> bool:
        path = self.object_path(artifact_id)
        files = self.manifest(artifact_id)
        if files is None or not path.is_dir():
            return False
        try:
            if list_files(path) != sorted(files):
                return False
            base = str(path)
            for rel, digest in files.items():
                if self.stat_cache.file_hash(f"{base}/{rel}", trust_cache) != digest:
                    return False
        except (OSError, ValueError):
            return False
        return tree_id(files.items()) == artifact_id

    def new_staging_dir(self, label: str = "stage", owner_pid: int | None = None) -> Path:
        """A new empty folder ``tmp/<label>-pid<PID>.<host>.<random>``; PID (default: this process)
        is the process whose death makes it garbage (see :meth:`clean_stale_staging`)."""
        pid = os.getpid() if owner_pid is None else owner_pid
        return Path(tempfile.mkdtemp(prefix=f"{label}-pid{pid}.{HOST}.", dir=self.root / "tmp"))

    def clean_stale_staging(self) -> list[Path]:
        """Remove staging folders whose owner process, on this host, is gone; returns them.

        Folders of live processes, of other hosts (a shared store) and without an owner in their
        name are kept (``gc`` removes those)."""
        removed = []
        for entry in sorted((self.root / "tmp").iterdir()):
            m = _STAGING_OWNER.search(entry.name)
            if m is None or m.group(2) != HOST or _pid_alive(int(m.group(1))):
                continue
            discard(entry)
            removed.append(entry)
        return removed

    def commit_dir(self, staged: str | os.PathLike) -> str:
        """Move a finished staging directory into the store; returns its artifact id.

        If the same content is already stored, the staged copy is discarded. A full disk raises
        :class:`DiskFullError` after removing the staged copy (nothing is half-committed: the
        manifest may be written, the object is not).
        """
        staged = Path(staged)
        try:
            return self._commit_dir(staged)
        except OSError as e:
            if not is_disk_full(e):
                raise
            need = tree_size(staged)
            discard(staged)
            raise DiskFullError(self.root, need) from None

    def _commit_dir(self, staged: Path) -> str:
        artifact_id, files = hash_tree(staged)
        if self.has(artifact_id):
            shutil.rmtree(staged, ignore_errors=True)
            return artifact_id
        target = self.object_path(artifact_id)
        target.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self._manifest_path(artifact_id), json.dumps({"id": artifact_id, "files": files}, indent=0))
        _make_read_only(staged)
        if target.exists():  # present but failed the check: corrupt or half-removed; set it aside
            self._quarantine(artifact_id)
        try:
            os.rename(staged, target)
        except OSError:
            if not self.has(artifact_id):  # another process won the race with the same content
                raise
            _make_writable(staged)
            shutil.rmtree(staged, ignore_errors=True)
        # Prime the stat cache with the hashes just computed, for the final paths.
        for rel, digest in files.items():
            self.stat_cache.remember(target / rel, digest)
        return artifact_id

    def import_path(self, src: str | os.PathLike, names: dict[str, str] | None = None) -> str:
        """Store a user's file or folder (a run input) and return its id.

        ``names`` maps stored relative names to source paths (default: a folder's files as they are,
        a single file as ``input<suffix>``). Nothing is copied when the content is already stored.
        """
        src = Path(src)
        if names is None:
            if src.is_dir():
                names = {rel: str(src / rel) for rel in list_files(src)}
            else:
                names = {f"input{src.suffix.lower()}": str(src)}
        if not names:
            raise ValueError(f"nothing to import from {src}")
        digests = {rel: self.stat_cache.file_hash(p) for rel, p in names.items()}
        artifact_id = tree_id(digests.items())
        if self.has(artifact_id):
            return artifact_id
        staged = self.new_staging_dir("import")
        try:
            for rel, p in names.items():
                dest = staged / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(p, dest)
        except OSError as e:
            discard(staged)
            if is_disk_full(e):
                raise DiskFullError(self.root, sum(os.path.getsize(p) for p in names.values())) from None
            raise
        return self.commit_dir(staged)

    def _quarantine(self, artifact_id: str) -> str:
        path = self.object_path(artifact_id)
        dest = self.root / "quarantine" / f"{artifact_id}-{int(time.time())}-{uuid.uuid4().hex[:6]}"
        if path.exists():
            _make_writable(path)
            os.rename(path, dest)
        self.stat_cache.forget(path)
        return str(dest)

    def all_ids(self) -> list[str]:
        objects = self.root / "objects"
        return sorted(p.name for shard in objects.iterdir() if shard.is_dir() for p in shard.iterdir())

    def verify(self, quarantine: bool = True) -> VerifyReport:
        """Re-read every object; corrupt ones are reported and (by default) moved to quarantine/."""
        corrupt, moved = [], []
        ids = self.all_ids()
        for artifact_id in ids:
            if not self._check(artifact_id, trust_cache=False):
                corrupt.append(artifact_id)
                if quarantine:
                    moved.append(self._quarantine(artifact_id))
        return VerifyReport(len(ids), corrupt, moved)

    # ------------------------------------------------------------------ stage-run records

    def _record_path(self, key: str) -> Path:
        return self.root / "runcache" / f"{_shard(key)}.json"

    def get_record(self, key: str) -> dict | None:
        """The record of a finished stage run, if it exists, is readable and all its outputs are intact."""
        try:
            record = json.loads(self._record_path(key).read_text())
            outputs = record["outputs"]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if not all(isinstance(i, str) and self.has(i) for i in outputs.values()):
            return None
        return record

    def put_record(self, key: str, record: dict) -> None:
        atomic_write_text(self._record_path(key), json.dumps(record, indent=1, sort_keys=True))

    def all_records(self) -> Iterator[tuple[Path, dict | None]]:
        for p in sorted((self.root / "runcache").glob("*/*.json")):
            try:
                yield p, json.loads(p.read_text())
            except (OSError, ValueError):
                yield p, None

    # ------------------------------------------------------------------ locks

    def key_lock(self, key: str) -> FileLock:
        return FileLock(str(self.root / "locks" / f"{key[:32]}.lock"))

    @contextlib.contextmanager
    def shared_use(self) -> Iterator[None]:
        """Held by every run: ``gc`` waits for no run to hold it."""
        with open(self.root / "locks" / "store.lock", "a+") as f:
            fcntl.flock(f, fcntl.LOCK_SH)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    @contextlib.contextmanager
    def exclusive_use(self, wait: bool = False) -> Iterator[None]:
        with open(self.root / "locks" / "store.lock", "a+") as f:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
            except BlockingIOError:
                raise StoreInUseError(f"the store {self.root} is in use by a running pipeline; try again later") from None
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    # ------------------------------------------------------------------ garbage collection

    def gc(self, referenced: set[str]) -> tuple[list[str], int]:
        """Remove objects not in ``referenced``, records whose outputs are gone, staging leftovers.

        Returns (removed ids, bytes freed). The caller holds :meth:`exclusive_use`.
        """
        removed, freed = [], 0
        for artifact_id in self.all_ids():
            if artifact_id in referenced:
                continue
            path = self.object_path(artifact_id)
            freed += sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
            _make_writable(path)
            shutil.rmtree(path)
            self._manifest_path(artifact_id).unlink(missing_ok=True)
            self.stat_cache.forget(path)
            removed.append(artifact_id)
        for p, record in self.all_records():
            outputs = (record or {}).get("outputs", {})
            if record is None or not all(self.object_path(i).is_dir() for i in outputs.values()):
                p.unlink(missing_ok=True)
        for leftover in (self.root / "tmp").iterdir():
            discard(leftover)
        return removed, freed


def discard(path: Path) -> None:
    """Remove a staging folder or file, read-only parts included; missing is fine."""
    if path.is_dir() and not path.is_symlink():
        for p in [path, *path.rglob("*")]:
            with contextlib.suppress(OSError):
                if not p.is_symlink():
                    p.chmod(0o755 if p.is_dir() else 0o644)
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def _make_read_only(path: Path) -> None:
    for p in [path, *path.rglob("*")]:
        if p.is_file():
            p.chmod(0o444)


def _make_writable(path: Path) -> None:
    if path.is_file():
        path.chmod(0o644)
        return
    for p in [path, *path.rglob("*")]:
        p.chmod(0o755 if p.is_dir() else 0o644)
