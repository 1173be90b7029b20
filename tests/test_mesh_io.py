"""core/io/mesh_io.py: numpy OBJ/PLY readers against trimesh (the reader they replace)."""

import numpy as np
import pytest

from progressive_avatars.core.io import mesh_io
from progressive_avatars.core.io.sequences import DataError, read_sequence
from tests.helpers import sphere_mesh


@pytest.mark.parametrize("kind", ["obj", "ply_binary", "ply_ascii"])
def test_reads_what_trimesh_reads(tmp_path, kind):
    trimesh = pytest.importorskip("trimesh")
    v, f = sphere_mesh(12, 16)
    v = v + np.random.default_rng(0).normal(0, 1e-3, v.shape)
    m = trimesh.Trimesh(v, f, process=False)
    path = tmp_path / ("m.obj" if kind == "obj" else "m.ply")
    if kind == "ply_ascii":
        path.write_bytes(trimesh.exchange.ply.export_ply(m, encoding="ascii"))
    else:
        m.export(path)
    ref = trimesh.load(path, force="mesh", process=False, maintain_order=True)
    got_v, got_f = mesh_io.read_mesh(path)
    np.testing.assert_allclose(got_v, np.asarray(ref.vertices), atol=1e-7, rtol=0)
    np.testing.assert_array_equal(got_f, np.asarray(ref.faces))
    np.testing.assert_array_equal(got_f, f)


def test_obj_quads_slashes_negative_indices_and_errors(tmp_path):
    p = tmp_path / "q.obj"
    p.write_text(
        "# comment\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0 1.0\nvt 0 0\nvn 0 0 1\n"
        "f 1/1/1 2/1/1 3/1/1 4/1/1\nf -4//1 -3//1 -1//1  # tail\n"
    )
    v, f = mesh_io.read_mesh(p)
    assert v.shape == (4, 3)
    assert f.tolist() == [[0, 1, 2], [2, 3, 0], [0, 1, 3]]  # quads split as trimesh splits them
    bad = tmp_path / "n.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 2 2\nf 1 2 3 4 5\n")
    with pytest.raises(ValueError, match=r"n\.obj: 1 face lines are neither triangles nor quads"):
        mesh_io.read_mesh(bad)
    out = tmp_path / "o.obj"
    out.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 9\n")
    with pytest.raises(ValueError, match=r"o\.obj: face vertex indices outside"):
        mesh_io.read_mesh(out)
    ply = tmp_path / "x.ply"
    ply.write_bytes(b"not a ply")
    with pytest.raises(DataError, match=r"x\.ply: not a PLY file"):
        read_sequence(ply)


def test_folder_of_mesh_npz_is_a_mesh_sequence(tmp_path):
    """A folder of per-frame mesh npz files reads as frames (it was taken for FLAME
    parameters and asked for a FLAME model)."""
    v, f = sphere_mesh(6, 8)
    d = tmp_path / "frames"
    d.mkdir()
    for i in (1, 2, 10):
        np.savez(d / f"frame_{i}.npz", vertices=v * i, faces=f)
    seq = read_sequence(d)
    assert seq.n_frames == 3 and seq.frame_ids.tolist() == [1, 2, 10]
    np.testing.assert_allclose(seq.vertices[2], v * 10, rtol=1e-6)
    np.savez(d / "frame_11.npz", vertices=np.stack([v, v]), faces=f)
    with pytest.raises(DataError, match=r"frame_11\.npz: holds 2 frames"):
        read_sequence(d)


HOSTILE_OBJ = {
    "index beyond int64": (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 99999999999999999999999999999\n", "more than 18 digits"),
    "absurd index": (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 1000000000\n", "indices outside"),
    "absurd negative index": (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 -1000000000\n", "indices outside"),
    "index 0": (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 0 1 2\n", "vertex 0"),
    "giant line": (b"v 0 0 " + b"1" * 200_000 + b"\nv 1 0 0\nv 1 1 0\nf 1 2 3\n", "line 1 is 200006 bytes"),
    "giant face line": (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf" + b" 1" * 100_000 + b"\n", "line 4"),
    "NaN vertex": (b"v 0 0 0\nv nan 0 0\nv 1 1 0\nf 1 2 3\n", "vertex 1 has a NaN"),
    "infinite vertex": (b"v 0 0 0\nv 1 0 0\nv 1 1e999 0\nf 1 2 3\n", "vertex 2 has a NaN or infinite"),
    "short vertex line": (b"v 0 0 0\nv 1 0\nv 1 1 0\nf 1 2 3\n", "fewer than 3 coordinates"),
}


@pytest.mark.parametrize("case", list(HOSTILE_OBJ))
def test_hostile_obj_is_refused_naming_the_file(tmp_path, case):
    data, why = HOSTILE_OBJ[case]
    p = tmp_path / "hostile.obj"
    p.write_bytes(data)
    with pytest.raises(mesh_io.MeshFormatError, match=r"hostile\.obj: .*" + why):
        mesh_io.read_mesh(p)
    with pytest.raises(DataError, match=r"hostile\.obj"):  # what a dataset or the add-on's import sees
        read_sequence(p)


def test_oversized_mesh_files_and_ply_counts_are_refused_before_reading(tmp_path, monkeypatch):
    v, f = sphere_mesh(6, 8)
    p = tmp_path / "big.obj"
    p.write_text(
        "".join(f"v {x} {y} {z}\n" for x, y, z in v) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f)
    )
    assert mesh_io.read_mesh(p)[0].shape == v.shape
    monkeypatch.setattr(mesh_io, "MAX_MESH_BYTES", p.stat().st_size - 1)
    with pytest.raises(mesh_io.MeshFormatError, match=r"big\.obj: mesh file of \d+ bytes, over the bound"):
        mesh_io.read_mesh(p)
    monkeypatch.undo()
    q = tmp_path / "counts.ply"
    for count in (b"1000000000000", b"1e12"):
        q.write_bytes(
            b"ply\nformat binary_little_endian 1.0\nelement vertex " + count + b"\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n" + bytes(24)
        )
        with pytest.raises(mesh_io.MeshFormatError, match=r"counts\.ply: "):
            mesh_io.read_mesh(q)


def test_mutated_obj_files_raise_only_format_errors(tmp_path):
    """Random byte changes, cuts and insertions in a valid OBJ: a mesh or a MeshFormatError
    naming the file, never another exception (MemoryError, OverflowError, IndexError...)."""
    v, f = sphere_mesh(4, 6)
    base = (
        "".join(f"v {x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in v)
        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f)
    ).encode()
    rng = np.random.default_rng(0)
    alphabet = np.frombuffer(b"0123456789-+. /\nfvenaNi#\t\r", np.uint8)
    p = tmp_path / "m.obj"
    for trial in range(300):
        b = bytearray(base)
        for _ in range(int(rng.integers(1, 6))):
            i = int(rng.integers(0, len(b)))
            op = trial % 3
            if op == 0:
                b[i] = int(rng.choice(alphabet))
            elif op == 1:
                b[i:i] = bytes(rng.choice(alphabet, int(rng.integers(1, 30))))
            else:
                del b[i : i + int(rng.integers(1, 40))]
        p.write_bytes(bytes(b))
        try:
            mv, mf = mesh_io.read_mesh(p)
        except mesh_io.MeshFormatError as exc:
            assert str(p) in str(exc)
            continue
        assert np.all(np.isfinite(mv)) and (len(mf) == 0 or (mf.min() >= 0 and mf.max() < len(mv)))
