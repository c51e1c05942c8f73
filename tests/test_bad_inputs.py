"""Bad input, as a user meets it through ``humanvdm run``: a clear error, and nothing lost.

Each case checks what a user sees and what stays behind: the exit code, one ``FAILED`` line that
names the file and the problem, the stage's log, no traceback, nothing half-written in the store
(no object, run record or staging folder from the failed stage), the other inputs of a batch done,
and a rerun that reuses what finished.

- One batch of photos made from ``examples/ryota.png`` (unreadable, truncated, 50 px, no person,
  cut off at the waist; and three that must work: 12,000 px tall, two people, a 16-bit grayscale
  TIFF with alpha stored rotated under an EXIF/TIFF orientation) runs ``--until diffuse`` at tiny
  settings, once for the module.
- A missing / unreadable weight file, a corrupt store entry and a run killed mid-stage use a tiny
  procedural scan (``render-training-orbits -> upscale``), which takes a second or two per stage.
- What messages call the user's files (their own paths, never the store's copies; an empty file;
  a file name in another script) uses the toy pipeline of tests/toyproject.py, and an empty photo
  the real one (it fails before any stage process starts).

Unit-level tests of the same cases: tests/test_perception.py (loading, detection), test_store.py
(corruption, verify), test_cli.py (toy-pipeline batch, kill and Ctrl-C), test_model_backends.py
(stage command lines with missing weights).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from humanvdm_core.frames import frame_paths, read_cameras, read_frames
from humanvdm_core.workflow.scheduler import read_lockfile
from humanvdm_core.workflow.store import Store
from testdata.procedural import write_person
from tests.toyproject import ToyProject

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
RYOTA = REPO / "examples" / "ryota.png"  # 512², black background (so its mask is where it is not black)
SIZE = 128  # the orbit's frame size in these tests
PHOTO_ARGS = ["--until", "diffuse", "--set", f"diffuse.resolution={SIZE}", "--set", "diffuse.fit_iterations=5",
              "--set", "diffuse.num_frames=3", "--no-progress"]
SCAN_ARGS = ["--set", "render-training-orbits.resolution=96", "--no-progress"]


def humanvdm(store: Path, *args: str, pipeline: Path | None = None, background: bool = False):
    """Run the ``humanvdm`` command; ``background`` returns the Popen (in its own process group)."""
    cmd = [sys.executable, "-m", "humanvdm_core.cli", args[0], "--store", str(store),
           *(["--pipeline", str(pipeline)] if pipeline else []), *args[1:]]
    if background:
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)
    return subprocess.run(cmd, capture_output=True, text=True, timeout=900)


def _ryota() -> np.ndarray:
    return cv2.imread(str(RYOTA), cv2.IMREAD_COLOR)  # BGR


def _ryota_mask() -> np.ndarray:
    return _ryota().max(axis=2) > 0  # IoU 0.995 with the PIFu ground-truth mask


def _records(store: Path) -> list[Path]:
    return sorted((store / "runcache").glob("*/*.json"))


def _input_view_alpha(store: Path, name: str) -> np.ndarray:
    """The coverage of the orbit's input view (the last frame, azimuth 0) of a finished diffuse run."""
    return read_frames(store / "runs" / name / "diffuse" / "orbit")[-1, ..., 3]


def _framed(mask: np.ndarray, size: int = SIZE, fill: float = 0.85) -> np.ndarray:
    """``mask`` placed as diffuse's input view places the person: its box ``fill`` of the frame, centred."""
    ys, xs = np.nonzero(mask)
    crop = mask[ys.min():ys.max() + 1, xs.min():xs.max() + 1].astype(np.float32)
    s = min(fill * size / crop.shape[0], 0.95 * size / crop.shape[1])
    h, w = round(crop.shape[0] * s), round(crop.shape[1] * s)
    out = np.zeros((size, size), np.float32)
    y0, x0 = (size - h) // 2, (size - w) // 2
    out[y0:y0 + h, x0:x0 + w] = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA)
    return out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a > 0.5, b > 0.5
    return float((a & b).sum() / max(1, (a | b).sum()))


# ----------------------------------------------------------------------------- command-line paths

def test_a_path_that_cannot_be_an_input_stops_the_command_before_anything_runs(tmp_path, monkeypatch, capsys):
    """A typo or a non-input on the command line fails at once (exit 2, one line), before any import or stage."""
    store = tmp_path / "artifacts"
    doc = tmp_path / "notes.pdf"
    doc.write_bytes(b"%PDF-1.4")
    cases = {str(tmp_path / "nope.png"): f"error: input not found: {tmp_path / 'nope.png'}",
             str(doc): f"error: {doc}: not an image",
             "/dev/null": "error: /dev/null: not a file or a folder"}
    for path, message in cases.items():
        res = humanvdm(store, "run", str(RYOTA), path, *PHOTO_ARGS)  # the good photo is not run either
        assert res.returncode == 2, res.stdout + res.stderr
        assert res.stderr.startswith(message) and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert Store(store).all_ids() == [] and _records(store) == []

    # a file the user may not read (cannot be made so for root: the read is made to fail)
    from humanvdm_core import cli
    from humanvdm_core.workflow.hashing import StatCache

    locked = tmp_path / "locked.png"
    locked.write_bytes(RYOTA.read_bytes())
    real = StatCache.file_hash

    def file_hash(self, path, *args, **kwargs):
        if Path(path) == locked:
            raise PermissionError(13, "Permission denied", str(path))
        return real(self, path, *args, **kwargs)

    monkeypatch.setattr(StatCache, "file_hash", file_hash)
    assert cli.main(["run", "--store", str(store), str(locked), *PHOTO_ARGS]) == 2
    assert capsys.readouterr().err == f"error: cannot read {locked}: Permission denied\n"


# ----------------------------------------------------------------------------- photos, one batch

def _write_gray16_alpha_rotated_tiff(path: Path) -> None:
    """ryota as 16-bit gray + straight alpha, stored turned 90° counter-clockwise, TIFF Orientation 6."""
    import OpenImageIO as oiio

    gray = cv2.cvtColor(_ryota(), cv2.COLOR_BGR2GRAY).astype(np.uint16) * 257
    alpha = _ryota_mask().astype(np.uint16) * 65535
    stored = np.ascontiguousarray(np.rot90(np.stack([gray, alpha], axis=2), k=1))
    spec = oiio.ImageSpec(stored.shape[1], stored.shape[0], 2, "uint16")
    spec.channelnames = ("Y", "A")
    spec.alpha_channel = 1
    spec.attribute("Orientation", 6)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), spec), oiio.geterror()
    out.write_image(stored)
    out.close()


def _make_photos(folder: Path) -> dict[str, Path]:
    folder.mkdir(parents=True)
    r = _ryota()
    p = {name: folder / name for name in ("broken.png", "cut.jpg", "tiny.png", "blank.png", "waist.png",
                                          "huge.jpg", "two.png", "odd.tif")}
    p["broken.png"].write_bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    ok, jpg = cv2.imencode(".jpg", r, [cv2.IMWRITE_JPEG_QUALITY, 90])
    p["cut.jpg"].write_bytes(jpg.tobytes()[: len(jpg) // 2])
    cv2.imwrite(str(p["tiny.png"]), cv2.resize(r, (50, 50), interpolation=cv2.INTER_AREA))
    cv2.imwrite(str(p["blank.png"]), np.full((256, 256, 3), 128, np.uint8))
    cv2.imwrite(str(p["waist.png"]), r[:230])  # cut just above the hips
    # 4782 x 12000 px (57 megapixels): the person's middle strip of ryota, upscaled
    cv2.imwrite(str(p["huge.jpg"]), cv2.resize(r[:, 150:354], (4782, 12000), interpolation=cv2.INTER_LINEAR),
                [cv2.IMWRITE_JPEG_QUALITY, 85])
    cv2.imwrite(str(p["two.png"]), np.concatenate([r, r[:, ::-1]], axis=1))
    _write_gray16_alpha_rotated_tiff(p["odd.tif"])
    return p


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """One ``humanvdm run`` over five unusable photos and three odd but usable ones, two jobs."""
    pytest.importorskip("mediapipe", reason="MediaPipe is not installed")
    pytest.importorskip("anny", reason="the 'anny' package is not installed")
    root = tmp_path_factory.mktemp("bad_photos")
    photos = _make_photos(root / "photos")
    store = root / "artifacts"
    res = humanvdm(store, "run", *map(str, photos.values()), "--jobs", "2", *PHOTO_ARGS)
    return photos, store, res


FAILURES = {  # photo -> what its FAILED line must say after the file's path
    "broken.png": ("cannot read {path}: ", "corrupt"),
    "cut.jpg": ("cannot read {path}: the file is truncated or corrupt",),
    "tiny.png": ("{path} is too small: 50x50 px", "at least 128 px"),
    "blank.png": ("no person found in {path}",),
    "waist.png": ("too little of the body is visible in {path}: left hip, right hip outside the photo "
                  "(cut off by the frame)",),
}


@pytest.mark.parametrize("photo", sorted(FAILURES))
def test_unusable_photo_fails_with_one_line_naming_the_file_and_the_problem(batch, photo):
    photos, store, res = batch
    name = Path(photo).stem
    lines = res.stdout.splitlines()
    failed = [ln for ln in lines if ln.startswith(f"FAILED {name}/")]
    assert len(failed) == 1, res.stdout + res.stderr
    assert failed[0].startswith(f"FAILED {name}/diffuse: diffuse: ")
    for part in FAILURES[photo]:
        assert part.format(path=photos[photo]) in failed[0], failed[0]
    assert "objects/" not in failed[0] and "input." not in failed[0], failed[0]  # never the store's copy
    log = store / "runs" / name / "logs" / "diffuse.log"
    assert lines[lines.index(failed[0]) + 1] == f"  log: {log}"
    text = log.read_text()
    assert "error: diffuse: " in text and "Traceback" not in text
    # nothing of the failed stage anywhere in the store: no output link, no lockfile, no staging folder
    assert not (store / "runs" / name / "diffuse").exists()
    assert read_lockfile(Store(store), name) == {}


def test_batch_goes_on_past_failures_and_keeps_only_complete_work(batch):
    photos, store, res = batch
    assert res.returncode == 1, res.stdout + res.stderr
    assert "Traceback" not in res.stdout + res.stderr
    assert "8 input(s): 3 stage run(s) ran, 0 cached, 5 failed, 0 skipped" in res.stdout
    for name in ("huge", "two", "odd"):
        assert f"outputs of {name}: {store / 'runs' / name}" in res.stdout
        assert read_lockfile(Store(store), name)["stages"]["diffuse"]["status"] == "ran"
        assert len(frame_paths(store / "runs" / name / "diffuse" / "orbit")) == 3
    s = Store(store)
    inputs = {s.import_path(p) for p in photos.values()}
    outputs = {read_lockfile(s, n)["stages"]["diffuse"]["outputs"]["orbit"] for n in ("huge", "two", "odd")}
    assert set(s.all_ids()) == inputs | outputs  # the 8 photos and 3 orbits, nothing else
    assert len(_records(store)) == 3
    assert list((store / "tmp").iterdir()) == []  # failed stages' staging folders are gone
    # a rerun reuses the finished work and fails the bad input again: a failure is never cached
    again = humanvdm(store, "run", str(photos["two.png"]), str(photos["broken.png"]), *PHOTO_ARGS)
    assert again.returncode == 1
    assert "2 input(s): 0 stage run(s) ran, 1 cached, 1 failed" in again.stdout


def test_12000_px_photo_is_downscaled_while_decoding_not_refused(batch):
    _, store, _ = batch
    log = (store / "runs" / "huge" / "logs" / "diffuse.log").read_text()
    assert "4782x12000 px is larger than 8192 px on the long side; downscaled by 2" in log
    assert _iou(_input_view_alpha(store, "huge"), _framed(_ryota_mask()[:, 150:354])) > 0.85
    # never decoded whole: a float copy at full size alone would add 690 MB over a 512² photo's run
    lock = Store(store)
    peak = {n: read_lockfile(lock, n)["stages"]["diffuse"]["peak_rss_mb"] for n in ("huge", "two")}
    assert peak["huge"] < peak["two"] + 450, peak  # measured: +270 MB


def test_two_people_keeps_the_largest_and_says_so(batch):
    photos, store, res = batch
    log = (store / "runs" / "two" / "logs" / "diffuse.log").read_text()
    assert "shows 2 people; using the largest one only" in log
    said = [ln for ln in res.stdout.splitlines() if ln.startswith("warning two/diffuse: ")
            and "using the largest one only" in ln]
    assert said, res.stdout  # on the console, naming the user's file (not the store's input.png) ...
    assert said[0].startswith(f"warning two/diffuse: {photos['two.png']} shows 2 people"), said[0]
    warnings = read_lockfile(Store(store), "two")["stages"]["diffuse"]["warnings"]
    assert any("using the largest one only" in w for w in warnings)  # ... and on record
    alpha = _input_view_alpha(store, "two")
    assert cv2.connectedComponents((alpha > 0.5).astype(np.uint8))[0] == 2  # background + one person
    assert _iou(alpha, _framed(_ryota_mask())) > 0.85


def test_gray_16bit_alpha_exif_rotated_photo_comes_out_upright_and_gray(batch):
    _, store, _ = batch
    frame = read_frames(store / "runs" / "odd" / "diffuse" / "orbit")[-1]
    alpha = frame[..., 3]
    assert _iou(alpha, _framed(_ryota_mask())) > 0.9  # upright (turned or flipped it would not match)
    inside = alpha > 0.99
    assert np.abs(frame[..., 0] - frame[..., 1])[inside].max() < 0.01  # gray stays gray
    assert np.abs(frame[..., 1] - frame[..., 2])[inside].max() < 0.01


# ----------------------------------------------------------------------------- a tiny scan

@pytest.fixture
def scan(tmp_path) -> Path:
    return write_person(tmp_path / "person", name="person", segments=12).parent


def test_missing_or_unreadable_weight_file_names_it_and_loses_the_finished_stage_nothing(tmp_path, scan):
    doc = yaml.safe_load((REPO / "pipeline.yaml").read_text())
    doc["stages"]["upscale"]["backend"] = "realesrgan"
    pipeline = tmp_path / "pipeline.yaml"
    pipeline.write_text(yaml.safe_dump(doc, sort_keys=False))
    store = tmp_path / "artifacts"
    missing = tmp_path / "weights" / "RealESRGAN_x4plus.pth"
    res = humanvdm(store, "run", str(scan), "--until", "upscale", *SCAN_ARGS,
                   "--set", f"upscale.realesrgan_weights={missing}", pipeline=pipeline)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "1 stage run(s) ran, 0 cached, 1 failed" in res.stdout
    (failed,) = [ln for ln in res.stdout.splitlines() if ln.startswith("FAILED ")]
    assert failed.startswith(f"FAILED person/upscale: upscale: missing weight file {missing}")
    assert "github.com/xinntao/Real-ESRGAN" in failed and "Traceback" not in res.stdout + res.stderr
    lock = read_lockfile(Store(store), "person")
    assert list(lock["stages"]) == ["render-training-orbits"] and len(_records(store)) == 1
    assert list((store / "tmp").iterdir()) == []

    garbage = tmp_path / "weights" / "garbage.pth"
    garbage.parent.mkdir()
    garbage.write_bytes(os.urandom(3000))
    res = humanvdm(store, "run", str(scan), "--until", "upscale", *SCAN_ARGS,
                   "--set", f"upscale.realesrgan_weights={garbage}", pipeline=pipeline)
    assert res.returncode == 1 and "0 stage run(s) ran, 1 cached, 1 failed" in res.stdout
    assert f"FAILED person/upscale: upscale: cannot read Real-ESRGAN RRDBNet weights checkpoint {garbage}" in res.stdout

    # back on the embedded backend the finished render is reused
    res = humanvdm(store, "run", str(scan), "--until", "upscale", *SCAN_ARGS, "--set", "upscale.target_size=128")
    assert res.returncode == 0 and "1 stage run(s) ran, 1 cached" in res.stdout, res.stdout + res.stderr


def test_corrupt_store_entry_is_never_a_cache_hit(tmp_path, scan):
    store = tmp_path / "artifacts"
    args = ["run", str(scan), "--until", "upscale", *SCAN_ARGS, "--set", "upscale.target_size=128"]
    first = humanvdm(store, *args)
    assert first.returncode == 0 and "2 stage run(s) ran" in first.stdout, first.stdout + first.stderr
    s = Store(store)
    lock = read_lockfile(s, "person")["stages"]
    orbit = lock["render-training-orbits"]["outputs"]["orbit"]
    frame = s.object_path(orbit) / "frames" / "0000.exr"
    good = frame.read_bytes()

    # 1. a damaged file (size and mtime change): the next run sees it and recomputes that stage only;
    #    the same bytes come back, so upscale stays cached (early cutoff)
    frame.chmod(0o644)
    frame.write_bytes(good[: len(good) // 2])
    res = humanvdm(store, *args)
    assert res.returncode == 0 and "1 stage run(s) ran, 1 cached" in res.stdout, res.stdout + res.stderr
    stages = read_lockfile(s, "person")["stages"]
    assert stages["render-training-orbits"]["status"] == "ran" and stages["upscale"]["status"] == "cached"
    assert stages["render-training-orbits"]["outputs"]["orbit"] == orbit and frame.read_bytes() == good

    # 2. silent damage (same size, mtime put back; the stat cache would see the new ctime at the next
    #    run): `humanvdm verify` finds it, quarantines it (nothing deleted), and the next run recomputes it
    st = frame.stat()
    frame.chmod(0o644)
    data = bytearray(good)
    data[len(data) // 2] ^= 0xFF
    frame.write_bytes(bytes(data))
    os.utime(frame, ns=(st.st_atime_ns, st.st_mtime_ns))
    verify = humanvdm(store, "verify")
    assert verify.returncode == 1 and "1 corrupt" in verify.stdout, verify.stdout + verify.stderr
    assert f"corrupt {orbit} -> moved to {store.resolve() / 'quarantine'}" in verify.stdout
    assert len(list((store / "quarantine").iterdir())) == 2  # step 1's damaged copy and this one
    res = humanvdm(store, *args)
    assert res.returncode == 0 and "1 stage run(s) ran, 1 cached" in res.stdout, res.stdout + res.stderr
    assert frame.read_bytes() == good

    # 3. an unreadable run record (truncated JSON) is a miss: that stage reruns
    upscale_key = read_lockfile(s, "person")["stages"]["upscale"]["key"]
    record = store / "runcache" / upscale_key[:2] / f"{upscale_key}.json"
    record.write_text(record.read_text()[:40])
    res = humanvdm(store, *args)
    assert res.returncode == 0 and "1 stage run(s) ran, 1 cached" in res.stdout
    assert read_lockfile(s, "person")["stages"]["upscale"]["status"] == "ran"
    verify = humanvdm(store, "verify")
    assert verify.returncode == 0 and "0 corrupt" in verify.stdout


def _wait_for(find, proc: subprocess.Popen, timeout: float = 120.0):
    end = time.time() + timeout
    while time.time() < end:
        found = find()
        if found:
            return found
        if proc.poll() is not None:
            raise AssertionError(f"the run ended before the stage got going:\n{proc.stdout.read()}")
        time.sleep(0.01)
    raise AssertionError("the stage never started writing")


def test_run_killed_mid_stage_leaves_nothing_complete_and_rerun_reuses_finished_stages(tmp_path, scan):
    store = tmp_path / "artifacts"
    args = ["run", str(scan), "--until", "upscale", *SCAN_ARGS, "--set", "upscale.target_size=768"]
    proc = humanvdm(store, *args, background=True)
    # the render finished; upscale has written its first frames into its staging folder
    partial = _wait_for(lambda: sorted((store / "tmp").glob("upscale-*/frames/frames/*.exr")), proc)
    os.killpg(proc.pid, signal.SIGKILL)  # the scheduler and the running stage
    proc.wait(timeout=30)
    proc.stdout.close()

    s = Store(store)
    lock = read_lockfile(s, "person")
    assert list(lock["stages"]) == ["render-training-orbits"]
    orbit = lock["stages"]["render-training-orbits"]["outputs"]["orbit"]
    assert set(s.all_ids()) == {lock["input"]["scan"]["id"], orbit}  # no upscale output in objects/
    assert len(_records(store)) == 1 and not (store / "runs" / "person" / "upscale").exists()
    assert partial[0].parent.parent.parent.parent == store / "tmp"  # the partial frames stayed in tmp/
    status = humanvdm(store, "status", str(scan), "--until", "upscale", *SCAN_ARGS[:-1],
                      "--set", "upscale.target_size=768")
    assert "render-training-orbits   up-to-date: cached" in status.stdout, status.stdout + status.stderr
    assert "upscale                  will-run: never run for this input" in status.stdout

    rerun = humanvdm(store, *args)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert "1 stage run(s) ran, 1 cached" in rerun.stdout
    assert not partial[0].exists() and list((store / "tmp").iterdir()) == []  # the rerun removed the dead run's
    stages = read_lockfile(s, "person")["stages"]
    assert stages["render-training-orbits"]["status"] == "cached" and stages["upscale"]["status"] == "ran"
    out = store / "runs" / "person" / "upscale" / "frames"
    assert len(frame_paths(out)) == 21 and read_cameras(out).width == 768
    verify = humanvdm(store, "verify")
    assert verify.returncode == 0 and "0 corrupt" in verify.stdout
    (store / "tmp" / "upscale-leftover").mkdir()  # staging garbage without an owner (an older store's): gc's
    with s.shared_use():  # as a running pipeline holds it: gc refuses, with a message, and removes nothing
        busy = humanvdm(store, "gc")
    assert busy.returncode == 2 and busy.stderr.startswith("error: the store ") and "in use" in busy.stderr
    assert "Traceback" not in busy.stderr and list((store / "tmp").iterdir())
    gc = humanvdm(store, "gc")
    assert gc.returncode == 0 and list((store / "tmp").iterdir()) == []


# ----------------------------------------------------------------------------- the user's file names

def test_errors_name_the_users_file_never_the_stores_copy(tmp_path):
    """A stage reads the store's copy (``objects/ab/<id>/input.txt``); what it says about it names the file
    the user gave, also where a library quoted the full path."""
    toy = ToyProject(tmp_path)
    src = tmp_path / "my texts" / "holiday.txt"
    src.parent.mkdir()
    src.write_text("BADFILE")
    res = humanvdm(toy.store.root, "run", str(src), "--kind", "text", "--no-progress", pipeline=toy.pipeline_path)
    assert res.returncode == 1, res.stdout + res.stderr
    (failed,) = [ln for ln in res.stdout.splitlines() if ln.startswith("FAILED ")]
    assert failed == (f"FAILED holiday/shout: shout: cannot read {src}: the file is truncated or corrupt "
                      f'(Failed to read "{src}")')
    assert "objects/" not in res.stdout and "input.txt" not in res.stdout


def test_an_empty_input_file_says_it_is_empty_and_the_batch_goes_on(tmp_path):
    toy = ToyProject(tmp_path)
    empty, good = tmp_path / "inputs" / "empty.txt", tmp_path / "inputs" / "good.txt"
    empty.write_bytes(b"")
    good.write_text("some text")
    res = humanvdm(toy.store.root, "run", str(empty), str(good), "--kind", "text", "--no-progress",
                   pipeline=toy.pipeline_path)
    assert res.returncode == 1, res.stdout + res.stderr
    assert "2 input(s): 3 stage run(s) ran, 0 cached, 1 failed, 2 skipped" in res.stdout
    lines = res.stdout.splitlines()
    (failed,) = [ln for ln in lines if ln.startswith("FAILED ")]
    assert failed == f"FAILED empty/shout: {empty} is empty (0 bytes)"
    assert read_lockfile(Store(toy.store.root), "good")["stages"]["report"]["status"] == "ran"
    # an empty photo, on the real pipeline: the same, before any stage process starts
    photo = tmp_path / "blank.jpg"
    photo.write_bytes(b"")
    res = humanvdm(tmp_path / "store", "run", str(photo), *PHOTO_ARGS)
    assert res.returncode == 1 and f"FAILED blank/diffuse: {photo} is empty (0 bytes)" in res.stdout, res.stdout


def test_a_file_name_in_any_script_keeps_a_readable_run_name(tmp_path):
    import unicodedata

    from humanvdm_core.inputs import discover

    names = {"Jürgen Müller.txt": "Jürgen_Müller", "写真 1.txt": "写真_1", "Ελένη.txt": "Ελένη",
             unicodedata.normalize("NFD", "José.txt"): "José", "a/b?.txt".replace("/", "_"): "a_b"}
    folder = tmp_path / "in"
    folder.mkdir()
    for name in names:
        (folder / name).write_text("text")
    got = {s.source.name: s.name for s in discover([folder / n for n in names], kind="text")}
    assert got == names
    toy = ToyProject(tmp_path / "toy")
    res = humanvdm(toy.store.root, "run", str(folder / "写真 1.txt"), "--kind", "text", "--no-progress",
                   pipeline=toy.pipeline_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"outputs of 写真_1: {toy.store.root / 'runs' / '写真_1'}" in res.stdout
    assert read_lockfile(Store(toy.store.root), "写真_1")["stages"]["report"]["status"] == "ran"
