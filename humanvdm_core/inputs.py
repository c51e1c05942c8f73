"""Turning what a user passes on the command line into subjects (run inputs) in the store.

- an image file (.png .jpg .jpeg .webp .bmp .tif .tiff .exr) -> a ``photo`` subject;
- a mesh file (.obj with its .mtl and textures, .glb, .gltf, .ply) or a folder holding one -> a ``scan``;
- a folder of images -> one ``photo`` subject per image (``*_mask.*`` files are skipped);
- a folder of scan folders (the THuman2.0 layout ``NNNN/NNNN.obj``) -> one ``scan`` per folder.

Subject names come from file or folder names, in any script ("Jürgen Müller.jpg" -> ``Jürgen_Müller``,
"写真.png" -> ``写真``; runs of spaces, slashes and other non-word characters become ``_``), and are made
unique within a batch. An empty input file is not refused here: its subject's first stage fails with
"PATH is empty (0 bytes)" and the rest of a batch runs.
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

from humanvdm_core.workflow.errors import HumanVDMError, InputError
from humanvdm_core.workflow.scheduler import Subject
from humanvdm_core.workflow.store import Store

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff", ".exr"}
MESH_SUFFIXES = {".obj", ".glb", ".gltf", ".ply"}


def _meshes_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)


def _is_mask(p: Path) -> bool:
    return p.stem.lower().endswith(("_mask", "_alpha"))


def discover(paths: list[str | Path], kind: str | None = None) -> list[Subject]:
    """Subjects for the given files/folders (not yet imported). ``kind`` forces photo or scan."""
    subjects: list[Subject] = []
    for raw in paths:
        p = Path(raw).expanduser()
        try:
            subjects.extend(_discover_one(p, kind))
        except OSError as e:  # e.g. a folder that cannot be listed
            raise InputError(f"cannot read {p}: {e.strerror or e}") from None
    if not subjects:
        raise InputError("no inputs given")
    _unique_names(subjects)
    return subjects


def _discover_one(p: Path, kind: str | None) -> list[Subject]:
    """The subjects one command-line path names."""
    if not p.exists():
        raise InputError(f"input not found: {p}")
    if p.is_file():
        suffix = p.suffix.lower()
        if kind is not None:
            return [Subject(p.stem, kind, p.resolve())]
        if suffix in IMAGE_SUFFIXES:
            return [Subject(p.stem, "photo", p.resolve())]
        if suffix in MESH_SUFFIXES:
            return [Subject(p.stem, "scan", p.resolve())]
        raise InputError(f"{p}: not an image ({sorted(IMAGE_SUFFIXES)}) nor a mesh ({sorted(MESH_SUFFIXES)})")
    if not p.is_dir():  # a device, a pipe, a socket
        raise InputError(f"{p}: not a file or a folder")
    if _meshes_in(p):
        return [Subject(p.name, kind or "scan", p.resolve())]
    images = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES and not _is_mask(f))
    scans = sorted(d for d in p.iterdir() if d.is_dir() and _meshes_in(d))
    if images and kind != "scan":
        return [Subject(f.stem, kind or "photo", f.resolve()) for f in images]
    if scans:
        return [Subject(d.name, kind or "scan", d.resolve()) for d in scans]
    raise InputError(f"{p}: no images, meshes or scan folders found")


def _unique_names(subjects: list[Subject]) -> None:
    seen: dict[str, int] = {}
    for s in subjects:
        base = re.sub(r"[^\w.-]+", "_", unicodedata.normalize("NFC", s.name)).strip("._") or "input"
        n = seen.get(base, 0)
        seen[base] = n + 1
        s.name = base if n == 0 else f"{base}-{n + 1}"


def import_subject(store: Store, subject: Subject) -> str | None:
    """Put the subject's files in the store (once) and set ``subject.input_id``.

    A file that cannot be read (permissions, I/O error) raises :class:`InputError` naming it; a full
    disk raises :class:`~humanvdm_core.workflow.errors.DiskFullError`. An empty file is not imported: it sets
    ``subject.error`` (its stages fail with it) and returns None."""
    src = subject.source
    try:
        if src.is_file() and src.stat().st_size == 0:
            subject.error = f"{src} is empty (0 bytes)"
            return None
        return _import(store, subject)
    except HumanVDMError:
        raise
    except OSError as e:
        where = Path(e.filename or subject.source)
        if where.is_relative_to(store.root):
            raise InputError(f"cannot write to the store {store.root}: {e.strerror or e} ({where})") from None
        raise InputError(f"cannot read {where}: {e.strerror or e}") from None


def _import(store: Store, subject: Subject) -> str:
    src = subject.source
    if src.is_file() and src.suffix.lower() == ".obj":
        names = {src.name: str(src)}
        names.update(_obj_sidecars(src))
        subject.input_id = store.import_path(src, names)
    elif src.is_file() and src.suffix.lower() in MESH_SUFFIXES:
        subject.input_id = store.import_path(src, {src.name: str(src)})
    else:
        subject.input_id = store.import_path(src)
    return subject.input_id


def _obj_sidecars(obj: Path) -> dict[str, str]:
    """The .mtl files an OBJ names and the texture files those name (relative to the OBJ)."""
    out: dict[str, str] = {}
    for line in obj.read_text(errors="replace").splitlines():
        if line.startswith("mtllib"):
            mtl = obj.parent / line.split(maxsplit=1)[1].strip()
            if mtl.is_file():
                out[mtl.relative_to(obj.parent).as_posix()] = str(mtl)
                for mline in mtl.read_text(errors="replace").splitlines():
                    parts = mline.strip().split()
                    if parts and parts[0].startswith("map_") and len(parts) > 1:
                        tex = obj.parent / parts[-1]
                        if tex.is_file():
                            out[tex.relative_to(obj.parent).as_posix()] = str(tex)
    return out
