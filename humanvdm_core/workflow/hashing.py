"""Content hashing with a stat cache.

A file's hash is the SHA-256 of its bytes. A directory artifact's id is the SHA-256 of its sorted
``relative/path <NUL> file-hash`` lines, so the id depends on content and names only.

Re-hashing big unchanged files is avoided as DVC does, with a stricter check. A small SQLite table
(:class:`StatCache`) maps a path to what it was when it was last hashed: inode, size, mtime_ns,
ctime_ns, an *edge fingerprint* (SHA-256 of the file's first and last :data:`EDGE_BYTES`, of the
whole file when it is at most twice that) and the full hash. A lookup that trusts the cache
returns the stored hash only when all four stat fields match AND the edge fingerprint, re-read
from the file at that moment, matches; otherwise the whole file is re-read. So:

- any change made through the file system is seen: a write, truncation, ``chmod`` or a restored
  mtime (``touch -d``, ``os.utime``) all set the ctime, which user code cannot set back;
- damage beneath the file system (bit rot, a raw-device write) that leaves the inode untouched is
  seen when it hits the first or last 64 KiB of a file, or anywhere in a file of at most 128 KiB;
- what no cheap check sees: such damage in the middle of a larger file. ``trust_cache=False``
  (``humanvdm verify``) re-reads every byte.

The cost is one ``open`` and at most 128 KiB read per file and lookup (measured in
benchmarks/README.md). The cache is shared by concurrent processes (SQLite locking).
"""

from __future__ import annotations

import hashlib
import os
import sqlite3
import threading
import time
from collections.abc import Iterable
from pathlib import Path

CHUNK = 1 << 22
EDGE_BYTES = 64 * 1024  # a cache hit re-reads this much of each end of every file


def hash_file(path: str | os.PathLike) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def edge_fingerprint(fd: int, size: int) -> str:
    """SHA-256 (first 32 hex digits) of the first and last :data:`EDGE_BYTES` of the open file ``fd``
    of ``size`` bytes, or of all of it when it is at most twice that (positional reads: the file
    offset is not moved)."""
    if size <= 2 * EDGE_BYTES:
        data = os.pread(fd, size, 0)
    else:
        data = os.pread(fd, EDGE_BYTES, 0) + os.pread(fd, EDGE_BYTES, size - EDGE_BYTES)
    return hashlib.sha256(data).hexdigest()[:32]


def hash_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def tree_id(entries: Iterable[tuple[str, str]]) -> str:
    """Id of a directory from its (relative posix path, file hash) pairs."""
    h = hashlib.sha256()
    for rel, digest in sorted(entries):
        h.update(rel.encode("utf-8") + b"\0" + digest.encode("ascii") + b"\n")
    return h.hexdigest()


def list_files(root: str | os.PathLike) -> list[str]:
    """Sorted relative posix paths of the regular files under ``root`` (links are refused)."""
    root = os.fspath(root)
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        rel_dir = os.path.relpath(dirpath, root)
        for name in dirnames:  # os.walk lists links to folders here and does not enter them
            if os.path.islink(os.path.join(dirpath, name)):
                raise ValueError(f"symbolic links are not allowed in artifacts: {os.path.join(dirpath, name)}")
        for name in filenames:
            full = os.path.join(dirpath, name)
            if os.path.islink(full):
                raise ValueError(f"symbolic links are not allowed in artifacts: {full}")
            out.append(name if rel_dir == "." else f"{rel_dir}/{name}".replace(os.sep, "/"))
    return sorted(out)


class StatCache:
    """path -> (inode, size, mtime_ns, ctime_ns, edge fingerprint, sha256), persisted in SQLite.

    Safe across processes and threads (one connection per thread). See the module docstring for
    exactly what a trusted lookup checks.
    """

    def __init__(self, db_path: str | os.PathLike | None):
        self.db_path = str(db_path) if db_path else None
        self._local = threading.local()
        self.hits = 0
        self.misses = 0

    def _conn(self) -> sqlite3.Connection | None:
        if self.db_path is None:
            return None
        conn = getattr(self._local, "conn", None)
        if conn is None:
            Path(self.db_path).parent.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(self.db_path, timeout=60, isolation_level=None)
            for attempt in range(200):  # switching to WAL can report "locked" while another process sets up
                try:
                    conn.execute("PRAGMA journal_mode=WAL")
                    conn.execute("CREATE TABLE IF NOT EXISTS files (path TEXT PRIMARY KEY, ino INTEGER, "
                                 "size INTEGER, mtime_ns INTEGER, ctime_ns INTEGER, edges TEXT, digest TEXT)")
                    conn.execute("DROP TABLE IF EXISTS hashes")  # the table of stores made before ctime/edges
                    break
                except sqlite3.OperationalError:
                    if attempt == 199:
                        raise
                    time.sleep(0.05)
            self._local.conn = conn
        return conn

    def file_hash(self, path: str | os.PathLike, trust_cache: bool = True) -> str:
        """The file's SHA-256: from the cache when its stat and edge fingerprint match, else re-read."""
        path = os.path.abspath(path)
        conn = self._conn()
        fd = os.open(path, os.O_RDONLY)
        try:
            st = os.fstat(fd)
            stat = (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
            if conn is not None and trust_cache:
                row = conn.execute("SELECT ino, size, mtime_ns, ctime_ns, edges, digest FROM files WHERE path=?",
                                   (path,)).fetchone()
                if row is not None and tuple(row[:4]) == stat and row[4] == edge_fingerprint(fd, st.st_size):
                    self.hits += 1
                    return row[5]
            self.misses += 1
            with open(fd, "rb", closefd=False) as f:
                digest = hashlib.file_digest(f, "sha256").hexdigest()
            if conn is not None:
                self._store(conn, (path, *stat, edge_fingerprint(fd, st.st_size), digest))
        finally:
            os.close(fd)
        return digest

    def remember(self, path: str | os.PathLike, digest: str) -> None:
        """Record a hash computed elsewhere for ``path`` as it is now on disk."""
        conn = self._conn()
        if conn is not None:
            path = os.path.abspath(path)
            fd = os.open(path, os.O_RDONLY)
            try:
                st = os.fstat(fd)
                self._store(conn, (path, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns,
                                   edge_fingerprint(fd, st.st_size), digest))
            finally:
                os.close(fd)

    @staticmethod
    def _store(conn: sqlite3.Connection, row: tuple) -> None:
        """Write one cache row; a failed write (e.g. a full disk) only costs a re-hash later."""
        try:
            conn.execute("INSERT OR REPLACE INTO files VALUES (?, ?, ?, ?, ?, ?, ?)", row)
        except sqlite3.Error:
            pass

    def forget(self, prefix: str | os.PathLike) -> None:
        conn = self._conn()
        if conn is not None:
            p = os.path.abspath(prefix)
            conn.execute("DELETE FROM files WHERE path = ? OR path LIKE ?", (p, p.rstrip("/") + "/%"))


def hash_tree(root: str | os.PathLike, cache: StatCache | None = None,
              trust_cache: bool = True) -> tuple[str, dict[str, str]]:
    """(directory id, {relative path: file hash}) of the files under ``root``."""
    root = Path(root)
    files = {}
    for rel in list_files(root):
        p = root / rel
        files[rel] = cache.file_hash(p, trust_cache) if cache else hash_file(p)
    return tree_id(files.items()), files
