"""Damaged or mismatched inputs that used to fail late, unclearly or not at all: a checkpoint
whose members are damaged, missing or of the wrong shape; an avatar file with a bad CRC; a
validation split tracking another mesh; OBJ relative indices in a file of several objects;
PLY files the numpy-only readers cannot read as they are."""

import json
import os
import shutil
import zipfile

import numpy as np
import pytest

from progressive_avatars.core.avatar.avatar import Avatar
from progressive_avatars.core.io.dataset import Dataset
from progressive_avatars.core.io.mesh_io import MeshFormatError, read_obj_bytes, read_ply_bytes
from progressive_avatars.core.io.sequences import DataError
from progressive_avatars.core.train.trainer import Trainer, config_for
from tests.helpers import sphere_mesh


@pytest.fixture(scope="module")
def checkpointed(tiny_dataset, tmp_path_factory):
    """A tiny run stopped with a checkpoint, and the settings to resume it."""
    cfg = config_for("tiny", iterations=4, checkpoint_every=2, eval_every=1000, log_every=1)
    run = tmp_path_factory.mktemp("ckpt_run")
    Trainer(tiny_dataset, str(run), cfg).run(progress=False)
    return str(run), cfg


def _rewrite(path, change):
    """Rewrite the npz ``path`` with change(members dict) applied."""
    with np.load(path, allow_pickle=False) as d:
        members = {k: d[k] for k in d.files}
    change(members)
    np.savez(path, **members)


def _flip_member_byte(path, member):
    """Flip one data byte of an (uncompressed) npz member in place: its CRC no longer matches."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(member + ".npy")
        raw = zf.read(info)
    blob = bytearray(open(path, "rb").read())
    at = blob.find(raw, info.header_offset)
    assert at > 0
    blob[at + len(raw) - 3] ^= 0xFF  # inside the array data, after the npy header
    open(path, "wb").write(bytes(blob))


def _short(name):
    return lambda m: m.update({name: m[name][:-2]})


def _drop(name):
    return lambda m: m.pop(name)


def _no_rng(m):
    state = json.loads(str(m["state_json"]))
    del state["rng"]
    m["state_json"] = np.array(json.dumps(state))


@pytest.mark.parametrize(
    "damage, message",
    [
        # the compiled Adam pass writes rows unchecked: a short moment would corrupt memory
        (_short("adam_m_d_mu"), r"member 'adam_m_d_mu' is float32\[\d+, 3\], expected a float array"),
        (_short("adam_steps"), r"member 'adam_steps' is float64\[\d+\]"),
        (_short("grad_sum"), r"member 'grad_sum' is float64\[\d+\]"),
        (_short("size_px"), r"member 'size_px'"),
        (_short("param_split_logits"), r"member 'param_split_logits'"),
        (_drop("grad_sum"), r"incomplete: grad_sum is not a file in the archive"),
        (_no_rng, r"incomplete: no entry 'rng'"),
        ("crc", r"member 'adam_v_d_mu' is damaged \(its CRC does not match\)"),
    ],
    ids=["adam_m", "adam_steps", "grad_sum", "size_px", "split_logits", "missing", "state", "crc"],
)
def test_damaged_checkpoint_is_refused_naming_the_file(checkpointed, tiny_dataset, tmp_path, damage, message):
    src, cfg = checkpointed
    run = tmp_path / "run"
    shutil.copytree(src, run)
    ckpt = str(run / "checkpoint.npz")
    if damage == "crc":
        _flip_member_byte(ckpt, "adam_v_d_mu")
    else:
        _rewrite(ckpt, damage)
    with pytest.raises(ValueError, match=message) as err:
        Trainer(tiny_dataset, str(run), cfg, resume=True, check_data=False)
    assert str(err.value).startswith(ckpt)
    # the undamaged checkpoint still resumes
    Trainer(tiny_dataset, src, cfg, resume=True, check_data=False)


def test_avatar_with_a_damaged_member_is_refused(tiny_run, tmp_path):
    path = str(tmp_path / "avatar.npz")
    shutil.copy(os.path.join(tiny_run, "avatar.npz"), path)
    Avatar.load(path)  # intact
    _flip_member_byte(path, "d_mu")
    with pytest.raises(ValueError, match=r"avatar\.npz: member 'd_mu' is damaged"):
        Avatar.load(path)


def test_validation_split_tracking_another_mesh_is_refused_before_training(tiny_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    verts, faces = sphere_mesh(2, 3)  # a valid mesh, but not the training split's
    np.savez(data / "val_mesh.npz", vertices=verts, faces=faces)
    meta_path = data / "transforms_val.json"
    meta = json.loads(meta_path.read_text())
    meta["canonical_mesh_path"] = "val_mesh.npz"
    meta_path.write_text(json.dumps(meta))
    Dataset(str(data), "val")  # the split alone is consistent
    cfg = config_for("tiny", iterations=2, eval_every=1)
    with pytest.raises(
        DataError, match=r"transforms_val\.json: its mesh \(\d+ vertices, \d+ faces\) is not .*transforms_train\.json's"
    ):
        Trainer(str(data), str(tmp_path / "run"), cfg, check_data=False)
    assert not os.path.exists(tmp_path / "run" / "checkpoint.npz")


def test_obj_relative_indices_count_back_from_their_own_line():
    obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 0 0 1\nv 1 0 1\nv 0 1 1\nf -3 -2 -1\nf 1 -1 -2\n"
    v, f = read_obj_bytes(obj, "two.obj")
    assert len(v) == 6
    assert f.tolist() == [[0, 1, 2], [3, 4, 5], [0, 5, 4]]
    with pytest.raises(MeshFormatError, match="negative one before the first vertex line"):
        read_obj_bytes(b"f -1 -2 -3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n", "early.obj")


def _ascii_ply(vertex_props, face_props, rows):
    head = ["ply", "format ascii 1.0", "element vertex 3", *[f"property float {p}" for p in vertex_props]]
    head += ["element face 1", *face_props, "end_header"]
    return ("\n".join(head + rows) + "\n").encode()


def test_mesh_ply_refusals_say_what_is_wrong():
    tri = ["0 0 0", "1 0 0", "0 1 0"]
    good = _ascii_ply("xyz", ["property list uchar int vertex_indices"], tri + ["3 0 1 2"])
    assert read_ply_bytes(good, "good.ply")[1].tolist() == [[0, 1, 2]]
    no_xyz = _ascii_ply(["px", "py", "pz"], ["property list uchar int vertex_indices"], tri + ["3 0 1 2"])
    with pytest.raises(MeshFormatError, match="noxyz.ply: vertex element lacks x, y, z"):
        read_ply_bytes(no_xyz, "noxyz.ply")
    coloured = _ascii_ply("xyz", ["property list uchar int vertex_indices", "property uchar red"], tri + ["3 0 1 2 9"])
    with pytest.raises(MeshFormatError, match="face element with properties besides its index list"):
        read_ply_bytes(coloured, "colour.ply")
    # a forged corner count is refused before it shapes an array
    head = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        b"property float z\nelement face 1\nproperty list uint int vertex_indices\nend_header\n"
    )
    body = np.zeros((3, 3), "<f4").tobytes() + np.array([4_000_000_000], "<u4").tobytes() + bytes(12)
    with pytest.raises(MeshFormatError, match="face 0 has 4000000000 corners"):
        read_ply_bytes(head + body, "huge.ply")


def test_numpy_splat_reader_refuses_other_elements(tmp_path, monkeypatch):
    """Without plyfile (as in Blender) an element before the vertex one was read as vertices."""
    import builtins

    from progressive_avatars.core.io import ply

    real_import = builtins.__import__

    def no_plyfile(name, *a, **k):
        if name == "plyfile":
            raise ImportError(name)
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_plyfile)
    props = ["x", "y", "z"]
    head = "ply\nformat binary_little_endian 1.0\nelement meta 1\nproperty float a\nelement vertex 2\n"
    head += "".join(f"property float {p}\n" for p in props) + "end_header\n"
    path = tmp_path / "meta_first.ply"
    path.write_bytes(head.encode() + np.arange(7, dtype="<f4").tobytes())
    with pytest.raises(ValueError, match=r"meta_first\.ply: element meta besides the vertex element"):
        ply._read_vertices(str(path))


def test_avatar_missing_a_coarse_array_is_refused(tiny_run, tmp_path):
    path = str(tmp_path / "avatar.npz")
    shutil.copy(os.path.join(tiny_run, "avatar.npz"), path)
    with np.load(path, allow_pickle=False) as d:
        assert "forest_root_ref" in d.files  # the tiny preset has coarse levels
    _rewrite(path, _drop("forest_coarse_faces"))
    with pytest.raises(ValueError, match=r"avatar\.npz: incomplete forest: .*forest_coarse_faces"):
        Avatar.load(path)


def test_forest_deeper_than_int8_levels_is_refused_by_the_checking_constructor():
    from progressive_avatars.core.avatar.forest import Forest

    def chain(depth):  # one template face, then a chain of splits ``depth`` deep (slot 0 each)
        parent = np.r_[-1, np.arange(depth)].astype(np.int64)
        slot = np.r_[-1, np.zeros(depth)].astype(np.int8)
        return Forest(np.array([[0, 1, 2]], np.int32), parent, slot, np.zeros((depth + 1, 3)))

    assert chain(127).level.max() == 127
    with pytest.raises(ValueError, match="deeper than level 127"):
        chain(128)


def test_writer_refuses_what_readers_refuse_as_too_many_root_faces(tiny_run, tiny_dataset, tmp_path, monkeypatch):
    from progressive_avatars.core.stream import writer

    avatar = Avatar.load(os.path.join(tiny_run, "avatar.npz"))
    rest = Dataset(tiny_dataset, "val").canonical_vertices
    writer.write_stream(str(tmp_path / "ok.pavs"), avatar, vertices=rest)
    monkeypatch.setattr(writer, "MAX_ROOT_FACES", len(avatar.forest.template_faces) - 1)
    with pytest.raises(ValueError, match=r"template faces .* a stream holds at most"):
        writer.write_stream(str(tmp_path / "big.pavs"), avatar, vertices=rest)
    assert not os.path.exists(tmp_path / "big.pavs")
