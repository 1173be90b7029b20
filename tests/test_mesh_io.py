"""core/io/mesh_io.py: numpy OBJ/PLY readers against trimesh (the reader they replace)."""

import struct

import numpy as np
import pytest

from progressive_avatars.core.io import mesh_io
from progressive_avatars.core.io.mesh_io import MeshFormatError, read_mesh
from progressive_avatars.core.io.sequences import (
    DataError,
    MeshSequence,
    natural_key,
    read_mesh_folder,
    read_mesh_npz,
    read_nersemble_tracking,
    read_sequence,
)
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


def _ascii_ply(vertex_props, vertex_rows, face_rows):
    head = ["ply", "format ascii 1.0", f"element vertex {len(vertex_rows)}"]
    head += [f"property float {p}" for p in vertex_props]
    head += [f"element face {len(face_rows)}", "property list uchar int vertex_indices", "end_header"]
    return ("\n".join(head + vertex_rows + face_rows) + "\n").encode()


def _binary_ply(fmt, verts, faces, end):
    head = (
        f"ply\nformat {fmt} 1.0\nelement vertex {len(verts)}\nproperty float x\nproperty float y\n"
        f"property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    body = b"".join(struct.pack(end + "fff", *v) for v in verts)
    body += b"".join(struct.pack(end + "B" + "i" * len(f), len(f), *f) for f in faces)
    return head + body


V3 = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 2.0, 0.0)]


def test_ply_face_naming_one_past_the_last_vertex_is_refused(tmp_path):
    p = tmp_path / "m.ply"
    p.write_bytes(_ascii_ply("xyz", ["0 0 0", "1 0 0", "0 2 0"], ["3 0 1 3"]))
    with pytest.raises(MeshFormatError, match="outside"):
        read_mesh(p)


def test_big_endian_binary_ply_reads_its_values(tmp_path):
    p = tmp_path / "be.ply"
    p.write_bytes(_binary_ply("binary_big_endian", V3, [(0, 1, 2)], ">"))
    v, f = read_mesh(p)
    np.testing.assert_array_equal(v, V3)
    np.testing.assert_array_equal(f, [[0, 1, 2]])


def test_ascii_ply_vertex_columns_follow_the_header_names(tmp_path):
    p = tmp_path / "zyx.ply"
    p.write_bytes(_ascii_ply(["nx", "z", "y", "x"], ["9 3 2 1", "9 6 5 4", "9 0 0 7"], ["3 0 1 2"]))
    v, _ = read_mesh(p)
    np.testing.assert_array_equal(v, [[1, 2, 3], [4, 5, 6], [7, 0, 0]])


def test_ply_pentagon_is_refused(tmp_path):
    p = tmp_path / "pent.ply"
    p.write_bytes(_ascii_ply("xyz", ["0 0 0", "1 0 0", "0 2 0", "1 1 0", "2 2 0"], ["5 0 1 2 3 4"]))
    with pytest.raises(MeshFormatError, match="5 corners"):
        read_mesh(p)


def test_binary_ply_one_byte_short_is_refused_by_name(tmp_path):
    data = _binary_ply("binary_little_endian", V3, [], "<")
    data = data.replace(b"element face 0\nproperty list uchar int vertex_indices\n", b"")
    p = tmp_path / "short.ply"
    p.write_bytes(data[:-1])
    with pytest.raises(MeshFormatError, match="more than the file holds"):
        read_mesh(p)


def test_binary_ply_mixed_corner_counts_are_refused(tmp_path):
    # Two rows of the same byte size whose counts differ (3 then 2).
    data = _binary_ply("binary_little_endian", V3, [(0, 1, 2)], "<")
    data = data.replace(b"element face 1", b"element face 2") + struct.pack("<Biii", 2, 0, 1, 2)
    p = tmp_path / "mixed.ply"
    p.write_bytes(data)
    with pytest.raises(MeshFormatError, match="different corner counts"):
        read_mesh(p)


def test_ascii_ply_mixed_corner_counts_are_refused(tmp_path):
    p = tmp_path / "mixed.ply"
    p.write_bytes(_ascii_ply("xyz", ["0 0 0", "1 0 0", "0 2 0"], ["3 0 1 2", "2 0 1 2"]))
    with pytest.raises(MeshFormatError, match="different corner counts"):
        read_mesh(p)


def test_obj_negative_indices_count_back_from_the_preceding_vertex_line(tmp_path):
    p = tmp_path / "two.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -3\nv 5 5 5\nv 6 5 5\nv 5 6 5\nf -3 -2 -1\n")
    _, f = read_mesh(p)
    np.testing.assert_array_equal(f, [[2, 1, 0], [3, 4, 5]])


FACES = np.array([[0, 1, 2]])


def _npz(tmp_path, T=3, **extra):
    v = np.arange(T * 9, dtype=np.float32).reshape(T, 3, 3)
    p = tmp_path / "m.npz"
    np.savez(p, vertices=v, faces=FACES, **extra)
    return p


@pytest.mark.parametrize("frame", [3, -4])
def test_frame_index_just_outside_the_sequence_is_refused(tmp_path, frame):
    with pytest.raises(DataError, match="out of range"):
        read_mesh_npz(_npz(tmp_path), frames=[frame])
    assert read_mesh_npz(_npz(tmp_path), frames=[-3]).frame_ids.tolist() == [0]


def test_fractional_float_frame_ids_fall_back_to_positions(tmp_path):
    assert read_mesh_npz(_npz(tmp_path, frame_ids=np.array([2.5, 7.5, 9.25]))).frame_ids.tolist() == [0, 1, 2]
    assert read_mesh_npz(_npz(tmp_path, frame_ids=np.array([4.0, 8.0, 12.0]))).frame_ids.tolist() == [4, 8, 12]


def test_mesh_folder_ids_are_the_last_number_of_each_name(tmp_path):
    for i in (10, 11):
        (tmp_path / f"cam2_frame{i}.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert read_mesh_folder(tmp_path).frame_ids.tolist() == [10, 11]


def test_natural_key_ignores_case():
    assert sorted(["B1.obj", "a2.obj", "A10.obj"], key=natural_key) == ["a2.obj", "A10.obj", "B1.obj"]


def test_nersemble_negative_scale_is_refused(tmp_path):
    p = tmp_path / "track.npz"
    np.savez(p, expression=np.zeros((2, 10)), shape=np.zeros((1, 300)), scale=np.array([-1.0]))
    with pytest.raises(DataError, match="positive"):
        read_nersemble_tracking(p, evaluate=False)


def test_mesh_sequence_checks_faces_and_frame_ids():
    v = np.zeros((2, 3, 3), np.float32)
    with pytest.raises(DataError, match="outside"):
        MeshSequence(np.array([[0, 1, 3]]), v, [0, 1])
    with pytest.raises(DataError, match="frame ids"):
        MeshSequence(FACES, v, [0, 1, 2])


def test_mesh_folder_parses_shared_obj_faces_once(tmp_path, monkeypatch):
    # A tracked OBJ sequence repeats every frame's face lines: a 1000-frame import spent three
    # quarters of its time (23 of 31 s at 8k faces) parsing them again. They are parsed once,
    # and again only for a frame whose text from its first face line on differs.
    v, f = sphere_mesh(6, 8)
    faces = "".join(f"f {a + 1}//1 {b + 1}//1 {c + 1}//1\n" for a, b, c in f)
    for t in range(4):
        vs = "".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in v * (1 + t))
        (tmp_path / f"frame{t}.obj").write_text(f"# frame {t}\n{vs}vn 0 0 1\n{faces}")
    quad = "# frame 4\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in v * 5) + "f 1 2 3 4\n" + faces.split("\n", 1)[1]
    (tmp_path / "frame4.obj").write_text(quad)  # same vertex count, one quad first: other faces
    parsed = []  # the files whose face lines the reader parsed

    class Counting:
        def findall(self, data):
            parsed.append(data.split(b"\n", 1)[0].decode())
            return real.findall(data)

    real = mesh_io._OBJ_TRI_QUAD
    monkeypatch.setattr(mesh_io, "_OBJ_TRI_QUAD", Counting())
    seq = read_mesh_folder(tmp_path, frames=[0, 1, 2, 3])
    assert parsed == ["# frame 0"]
    np.testing.assert_array_equal(seq.faces, f)
    np.testing.assert_allclose(seq.vertices[3], v * 4, atol=1e-5)
    with pytest.raises(DataError, match=r"frame4\.obj: faces differ from frame0\.obj"):
        read_mesh_folder(tmp_path)
    assert parsed[-1] == "# frame 4", parsed
    # negative indices resolve against the vertex lines before each face line: the same text
    # after another number of vertices is parsed again
    a, b = tmp_path / "neg" / "a.obj", tmp_path / "neg" / "b.obj"
    a.parent.mkdir()
    a.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n")
    b.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf -3 -2 -1\n")
    reuse = {}
    assert read_mesh(a, reuse)[1].tolist() == [[0, 1, 2]]
    assert read_mesh(b, reuse)[1].tolist() == [[1, 2, 3]]
