"""The artifact store: content ids, atomic commits, stat cache, corruption, verify, gc, io formats."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from humanvdm_core.io import read_exr, read_npz, write_exr, write_npz
from humanvdm_core.workflow.hashing import StatCache, hash_tree
from humanvdm_core.workflow.scheduler import CACHED, RAN, referenced_ids
from humanvdm_core.workflow.store import Store
from tests.toyproject import ToyProject


def make_dir(root, files: dict[str, bytes]):
    for rel, data in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    return root


def test_directory_id_depends_on_names_and_content_only(tmp_path):
    a = make_dir(tmp_path / "a", {"x.bin": b"1", "sub/y.bin": b"2"})
    b = make_dir(tmp_path / "b", {"sub/y.bin": b"2", "x.bin": b"1"})
    c = make_dir(tmp_path / "c", {"x.bin": b"1", "sub/z.bin": b"2"})
    assert hash_tree(a)[0] == hash_tree(b)[0] != hash_tree(c)[0]


def test_commit_is_deduplicated_and_read_only(tmp_path):
    store = Store(tmp_path / "store")
    ids = []
    for _ in range(2):
        staged = store.new_staging_dir()
        make_dir(staged, {"f.txt": b"same"})
        ids.append(store.commit_dir(staged))
        assert not staged.exists()
    assert ids[0] == ids[1] and store.all_ids() == [ids[0]]
    f = store.object_path(ids[0]) / "f.txt"
    assert f.read_bytes() == b"same" and not os.access(f, os.W_OK) or os.geteuid() == 0
    assert f.stat().st_mode & 0o222 == 0


def test_stat_cache_avoids_rereading_unchanged_files(tmp_path):
    d = make_dir(tmp_path / "d", {f"{i}.bin": os.urandom(1000) for i in range(20)})
    cache = StatCache(tmp_path / "h.db")
    first = hash_tree(d, cache)
    assert cache.misses == 20
    again = hash_tree(d, cache)
    assert again == first and cache.misses == 20 and cache.hits == 20
    (d / "3.bin").write_bytes(b"changed")
    third = hash_tree(d, cache)
    assert cache.misses == 21 and third[0] != first[0]
    # a fresh cache object on the same database sees the same entries (persisted, shared by processes)
    other = StatCache(tmp_path / "h.db")
    assert hash_tree(d, other) == third and other.misses == 0


def test_import_does_not_copy_known_content(tmp_path):
    store = Store(tmp_path / "store")
    src = tmp_path / "photo.png"
    src.write_bytes(b"png bytes")
    a = store.import_path(src)
    assert sorted(os.listdir(store.object_path(a))) == ["input.png"]
    copy = tmp_path / "renamed.PNG"
    copy.write_bytes(b"png bytes")
    assert store.import_path(copy) == a  # content, not name, decides


def _toy_run(toy, subj, **kw):
    return {r.stage: r for r in toy.scheduler(**kw).run([subj]).runs}


def test_modified_object_is_never_a_cache_hit(tmp_path):
    toy = ToyProject(tmp_path)
    subj = toy.subject("a", "hello there")
    runs = _toy_run(toy, subj)
    f = toy.store.object_path(runs["measure"].outputs["out"]) / "n.txt"
    f.chmod(0o644)
    f.write_text("999")
    runs2 = _toy_run(toy, subj)
    assert runs2["shout"].state == CACHED and runs2["measure"].state == RAN
    assert (toy.store.object_path(runs2["measure"].outputs["out"]) / "n.txt").read_text() == "1"


def _damage_keeping_size_and_mtime(f, offset: int) -> None:
    """Flip one byte at ``offset``, then put the mtime back: size, inode and mtime are unchanged."""
    st = f.stat()
    f.chmod(0o644)
    data = bytearray(f.read_bytes())
    data[offset] ^= 0xFF
    f.write_bytes(bytes(data))
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    f.chmod(0o444)


def test_damage_with_size_and_mtime_restored_is_never_a_cache_hit(tmp_path):
    """The stat cache keys on the ctime too (a write, a chmod or a restored mtime all change it), so a
    file damaged through the file system is re-hashed at the next lookup and its stage recomputed."""
    toy = ToyProject(tmp_path)
    subj = toy.subject("a", "hello there")
    runs = _toy_run(toy, subj)
    shout_id = runs["shout"].outputs["out"]
    f = toy.store.object_path(shout_id) / "text.txt"
    _damage_keeping_size_and_mtime(f, 4)
    assert not Store(toy.store.root).has(shout_id)
    runs2 = _toy_run(toy, subj)
    assert runs2["shout"].state == RAN and runs2["measure"].state == CACHED  # same bytes back: early cutoff
    assert f.read_text() == "hello there"


def test_cache_hit_rechecks_the_head_and_tail_bytes_of_every_file(tmp_path):
    """Even when every stat field matches (damage beneath the file system: simulated by giving the
    stat-cache row the damaged file's stat), a cache hit re-reads each file's first and last 64 KiB
    (small files whole); the middle of a large file is only checked by ``verify``."""
    from humanvdm_core.workflow.hashing import EDGE_BYTES

    store = Store(tmp_path / "store")
    staged = store.new_staging_dir()
    size = 4 * EDGE_BYTES
    make_dir(staged, {"big.bin": os.urandom(size), "small.bin": os.urandom(100)})
    artifact_id = store.commit_dir(staged)
    obj = store.object_path(artifact_id)

    def stat_unchanged(f) -> None:  # as if the damage had left no trace in the inode
        st = f.stat()
        store.stat_cache._conn().execute("UPDATE files SET mtime_ns=?, ctime_ns=? WHERE path=?",
                                         (st.st_mtime_ns, st.st_ctime_ns, str(f)))

    for rel, offset in (("big.bin", 10), ("big.bin", size - 10), ("small.bin", 50)):
        f = obj / rel
        _damage_keeping_size_and_mtime(f, offset)
        stat_unchanged(f)
        assert not Store(store.root).has(artifact_id), (rel, offset)
        _damage_keeping_size_and_mtime(f, offset)  # repaired: the same bytes as committed
        store.stat_cache.file_hash(f, trust_cache=False)
        assert Store(store.root).has(artifact_id)
    f = obj / "big.bin"
    _damage_keeping_size_and_mtime(f, size // 2)  # the middle: what the cheap check does not read
    stat_unchanged(f)
    assert Store(store.root).has(artifact_id)
    assert Store(store.root).verify().corrupt == [artifact_id]


def test_verify_finds_silent_corruption_and_the_run_recomputes_it(tmp_path):
    toy = ToyProject(tmp_path)
    subj = toy.subject("a", "hello there")
    runs = _toy_run(toy, subj)
    f = toy.store.object_path(runs["shout"].outputs["out"]) / "text.txt"
    st = f.stat()
    f.chmod(0o644)
    f.write_text("hellO there")  # same size; then restore the mtime: the stat cache cannot notice
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    report = Store(toy.store.root).verify()
    assert report.corrupt == [runs["shout"].outputs["out"]]
    assert report.quarantined and os.path.isdir(report.quarantined[0])  # set aside, not deleted
    runs2 = _toy_run(toy, subj)
    assert runs2["shout"].state == RAN and runs2["measure"].state == CACHED
    assert Store(toy.store.root).verify().corrupt == []


def test_unreadable_run_record_is_recomputed(tmp_path):
    toy = ToyProject(tmp_path)
    subj = toy.subject("a", "abc")
    runs = _toy_run(toy, subj)
    record = toy.store._record_path(runs["report"].key)
    record.write_text('{"outputs": {"out": ')  # truncated JSON
    assert _toy_run(toy, subj)["report"].state == RAN
    assert json.loads(record.read_text())["outputs"] == runs["report"].outputs


def test_gc_removes_only_unreferenced_artifacts(tmp_path):
    toy = ToyProject(tmp_path)
    subj = toy.subject("a", "x" * 25)
    old = _toy_run(toy, subj)
    new = _toy_run(toy, subj, overrides={"measure": {"bucket": 5}})
    keep = referenced_ids(toy.store)
    assert old["measure"].outputs["out"] not in keep and new["measure"].outputs["out"] in keep
    with toy.store.exclusive_use():
        removed, _ = toy.store.gc(keep)
    assert set(removed) == {old["measure"].outputs["out"], old["report"].outputs["out"]}
    again = _toy_run(toy, subj, overrides={"measure": {"bucket": 5}})
    assert {r.state for r in again.values()} == {CACHED}


def test_a_run_removes_the_staging_folders_of_dead_processes_of_its_host_only(tmp_path):
    import subprocess
    import sys

    from humanvdm_core.workflow.store import HOST

    store = Store(tmp_path / "s")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)  # a process that has ended
    stale = store.new_staging_dir("upscale", owner_pid=dead_pid)
    make_dir(stale, {"frames/0000.exr": b"partial"})
    (stale / "frames" / "0000.exr").chmod(0o444)
    mine = store.new_staging_dir("upscale")  # this live process's
    elsewhere = store.root / "tmp" / f"upscale-pid{dead_pid}.{HOST}x.abc"  # another host's: its pids mean nothing here
    unnamed = store.root / "tmp" / "upscale-abc"  # an older store's: gc's business
    for d in (elsewhere, unnamed):
        d.mkdir()
    assert store.clean_stale_staging() == [stale]
    assert not stale.exists() and mine.exists() and elsewhere.exists() and unnamed.exists()


def test_gc_refuses_while_a_run_holds_the_store(tmp_path):
    store = Store(tmp_path / "s")
    with store.shared_use():
        with pytest.raises(RuntimeError, match="in use"):
            with store.exclusive_use():
                pass


def test_npz_is_deterministic_and_schema_checked(tmp_path):
    arrays = {"a": np.arange(5.0), "b": np.eye(3, dtype=np.float32), "name": np.array("anny")}
    write_npz(tmp_path / "1.npz", arrays, "test.schema", 2)
    write_npz(tmp_path / "2.npz", arrays, "test.schema", 2)
    assert (tmp_path / "1.npz").read_bytes() == (tmp_path / "2.npz").read_bytes()
    back = read_npz(tmp_path / "1.npz", "test.schema", 2)
    assert str(back["name"]) == "anny" and np.array_equal(back["b"], arrays["b"])
    with pytest.raises(ValueError, match="schema version 2"):
        read_npz(tmp_path / "1.npz", "test.schema", 3)
    with pytest.raises(ValueError, match="expected schema"):
        read_npz(tmp_path / "1.npz", "other")


def test_exr_roundtrip_half_with_attributes(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.random((6, 7, 4)).astype(np.float32)
    write_exr(tmp_path / "a.exr", img, attrs={"stage": "test", "frame_index": 3})
    write_exr(tmp_path / "b.exr", img, attrs={"stage": "test", "frame_index": 3})
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    back, attrs = read_exr(tmp_path / "a.exr", with_attrs=True)
    assert back.shape == (6, 7, 4)
    assert np.abs(back - img).max() < 1e-3  # half precision
    assert attrs["humanvdm:stage"] == "test" and attrs["humanvdm:frame_index"] == 3
    assert attrs["oiio:ColorSpace"] and attrs["channels"] == ["R", "G", "B", "A"]
    assert len(attrs["humanvdm:pixel_hash"]) == 32


def test_links_are_refused_in_artifacts(tmp_path):
    d = make_dir(tmp_path / "d", {"a.txt": b"a"})
    (d / "linked_dir").symlink_to(tmp_path)
    with pytest.raises(ValueError, match="symbolic links"):
        hash_tree(d)


def test_exr_write_on_a_full_disk_is_enospc_and_leaves_no_file(tmp_path):
    """OpenImageIO says only "File output failed"; write_exr reports ENOSPC (what the stage turns into
    exit 4 and the scheduler into its one-line message) and removes its temporary file."""
    import sys

    from tests.toyproject import in_tiny_filesystem

    mount = tmp_path / "small"
    code = ("import errno, os, numpy as np; from humanvdm_core.io import write_exr\n"
            "try:\n"
            f"    write_exr('{mount}/a.exr', np.random.default_rng(0).random((512, 512, 4)))\n"
            "except OSError as e:\n"
            "    print('errno', e.errno, errno.errorcode.get(e.errno), 'files', os.listdir('" + str(mount) + "'))\n")
    res = in_tiny_filesystem(mount, "256k", f"{sys.executable} -c \"{code}\"")
    if res is None:
        pytest.skip("cannot mount a tmpfs in a private namespace here (unshare)")
    assert "errno 28 ENOSPC files []" in res.stdout, res.stdout + res.stderr
