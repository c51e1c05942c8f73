"""Turning command-line inputs into subjects and importing them into the store."""

from __future__ import annotations

import os

import pytest

from humanvdm_core.inputs import discover, import_subject
from humanvdm_core.workflow.errors import InputError
from humanvdm_core.workflow.store import Store


def touch(path, data=b"x"):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def test_kinds_from_files_and_folders(tmp_path):
    photo = touch(tmp_path / "me.JPG")
    touch(tmp_path / "photos" / "a.png")
    touch(tmp_path / "photos" / "a_mask.png")
    touch(tmp_path / "photos" / "b.webp")
    touch(tmp_path / "photos" / "notes.txt")
    touch(tmp_path / "thuman" / "0001" / "0001.obj")
    touch(tmp_path / "thuman" / "0002" / "0002.obj")
    glb = touch(tmp_path / "char.glb")
    subjects = discover([photo, tmp_path / "photos", tmp_path / "thuman", glb])
    assert [(s.name, s.kind) for s in subjects] == [
        ("me", "photo"), ("a", "photo"), ("b", "photo"), ("0001", "scan"), ("0002", "scan"), ("char", "scan")]


def test_names_are_unique_in_a_batch(tmp_path):
    a = touch(tmp_path / "x" / "photo.png")
    b = touch(tmp_path / "y" / "photo.png", b"y")
    assert [s.name for s in discover([a, b])] == ["photo", "photo-2"]


@pytest.mark.parametrize("make,message", [
    (lambda p: p / "missing.png", "input not found"),
    (lambda p: touch(p / "doc.pdf"), "not an image"),
    (lambda p: (p / "empty").mkdir() or p / "empty", "no images, meshes or scan folders"),
])
def test_unusable_inputs_are_clear_errors(tmp_path, make, message):
    with pytest.raises(InputError, match=message):
        discover([make(tmp_path)])


def test_obj_imports_with_its_material_and_texture(tmp_path):
    scan = tmp_path / "scan"
    touch(scan / "body.obj", b"mtllib body.mtl\nv 0 0 0\n")
    touch(scan / "body.mtl", b"newmtl m\nmap_Kd tex/skin.jpg\n")
    touch(scan / "tex" / "skin.jpg", b"jpeg")
    touch(scan / "unrelated_big_file.bin", os.urandom(100))
    store = Store(tmp_path / "store")
    (subject,) = discover([scan / "body.obj"])
    artifact_id = import_subject(store, subject)
    assert store.manifest(artifact_id).keys() == {"body.obj", "body.mtl", "tex/skin.jpg"}


def test_photo_import_is_by_content(tmp_path):
    store = Store(tmp_path / "store")
    a = touch(tmp_path / "one.png", b"same pixels")
    b = touch(tmp_path / "two.png", b"same pixels")
    sa, sb = discover([a, b])
    assert import_subject(store, sa) == import_subject(store, sb)
