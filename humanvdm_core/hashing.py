"""Content hashing with a stat cache.

A file's hash is the SHA-256 of its bytes. A directory artifact's id is the SHA-256 of its sorted
``relative/path <NUL> file-hash`` lines, so the id depends on content and names only.

Re-hashing big unchanged files is avoided as DVC does: a small SQLite table maps
(path, inode, size, mtime_ns) to the file's hash. A file whose stat changed is re-read; a full
``verify`` bypasses the cache. The cache is shared by concurrent processes (SQLite locking).
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


def hash_file(path: str | os.PathLike) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


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
    """(path, inode, size, mtime_ns) -> sha256, persisted in SQLite; safe across processes."""

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
                    conn.execute("CREATE TABLE IF NOT EXISTS hashes (path TEXT PRIMARY KEY, ino INTEGER, "
                                 "size INTEGER, mtime_ns INTEGER, digest TEXT)")
                    break
                except sqlite3.OperationalError:
                    if attempt == 199:
                        raise
                    time.sleep(0.05)
            self._local.conn = conn
        return conn

    def file_hash(self, path: str | os.PathLike, trust_cache: bool = True) -> str:
        path = os.path.abspath(path)
        st = os.stat(path)
        conn = self._conn()
        if conn is not None and trust_cache:
            row = conn.execute("SELECT ino, size, mtime_ns, digest FROM hashes WHERE path=?", (path,)).fetchone()
            if row is not None and tuple(row[:3]) == (st.st_ino, st.st_size, st.st_mtime_ns):
                self.hits += 1
                return row[3]
        self.misses += 1
        digest = hash_file(path)
        if conn is not None:
            conn.execute("INSERT OR REPLACE INTO hashes VALUES (?, ?, ?, ?, ?)",
                         (path, st.st_ino, st.st_size, st.st_mtime_ns, digest))
        return digest

    def remember(self, path: str | os.PathLike, digest: str) -> None:
        """Record a hash computed elsewhere for ``path`` as it is now on disk."""
        conn = self._conn()
        if conn is not None:
            path = os.path.abspath(path)
            st = os.stat(path)
            conn.execute("INSERT OR REPLACE INTO hashes VALUES (?, ?, ?, ?, ?)",
                         (path, st.st_ino, st.st_size, st.st_mtime_ns, digest))

    def forget(self, prefix: str | os.PathLike) -> None:
        conn = self._conn()
        if conn is not None:
            p = os.path.abspath(prefix)
            conn.execute("DELETE FROM hashes WHERE path = ? OR path LIKE ?", (p, p.rstrip("/") + "/%"))


def hash_tree(root: str | os.PathLike, cache: StatCache | None = None,
              trust_cache: bool = True) -> tuple[str, dict[str, str]]:
    """(directory id, {relative path: file hash}) of the files under ``root``."""
    root = Path(root)
    files = {}
    for rel in list_files(root):
        p = root / rel
        files[rel] = cache.file_hash(p, trust_cache) if cache else hash_file(p)
    return tree_id(files.items()), files
