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
