"""Spherical-harmonic colour (degree 0..3): the basis, the avatar, PLY, stream and training."""

import json

import numpy as np
import pytest
import torch

from progressive_avatars.core.geometry import sh
from progressive_avatars.core.avatar.avatar import Avatar, sh_to_rgb
from progressive_avatars.core.io.ply import read_ply, write_ply
from progressive_avatars.core.stream.reader import read_stream
from progressive_avatars.core.stream.writer import write_stream
from tests.helpers import random_forest, sphere_mesh


def fibonacci_sphere(n):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def test_basis_is_orthonormal_over_the_sphere():
    d = fibonacci_sphere(200_000)
    Y = np.concatenate([np.full((len(d), 1), sh.SH_C0), sh.rest_basis(d, 3, np.stack)], 1)  # [n,16]
    gram = 4 * np.pi * (Y.T @ Y) / len(d)
    np.testing.assert_allclose(gram, np.eye(16), atol=2e-3)
    assert [sh.num_rest(k) for k in range(4)] == [0, 3, 8, 15]
    with pytest.raises(ValueError, match="0..3"):
        sh.num_rest(4)


def test_numpy_and_torch_agree_and_degrees_truncate():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dc, rest = rng.normal(size=(50, 3)), rng.normal(size=(50, 15, 3))
    a = sh.sh_rgb(dc, rest, d, np.stack)
    b = sh.sh_rgb(torch.tensor(dc), torch.tensor(rest), torch.tensor(d), torch.stack).numpy()
    np.testing.assert_allclose(a, b, atol=1e-12)
    np.testing.assert_allclose(sh.sh_rgb(dc, rest, d, np.stack, degree=1), sh.sh_rgb(dc, rest[:, :3], d, np.stack))
    np.testing.assert_allclose(sh.sh_rgb(dc, rest, d, np.stack, degree=0), 0.5 + sh.SH_C0 * dc)


def sh_avatar(degree=2, seed=1):
    rng = np.random.default_rng(seed)
    v, f = sphere_mesh(6, 8, radius=0.1)
    forest = random_forest(f, rng, depth=2, frac=0.5)
    av = Avatar.initial(forest)
    N = forest.num_faces
    av.f_dc[:] = rng.normal(0, 0.5, (N, 3))
    av.f_rest = rng.normal(0, 0.3, (N, sh.num_rest(degree), 3)).astype(np.float32)
    return v, Avatar(forest, av.d_mu, av.d_log_scale, av.d_rot, av.opacity_logit, av.f_dc, f_rest=av.f_rest)


def test_avatar_colours_depend_on_the_view_and_survive_save(tmp_path):
    v, av = sh_avatar()
    assert av.sh_degree == 2
    front = av.gaussians(v, camera_center=[0, 0, 1.0])["colors"]
    side = av.gaussians(v, camera_center=[1.0, 0, 0])["colors"]
    assert np.abs(front - side).max() > 0.05
    means = av.gaussians(v)["means"]
    d = means - np.array([0, 0, 1.0])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    want = np.maximum(sh.sh_rgb(av.f_dc.astype(np.float64), av.f_rest.astype(np.float64), d, np.stack), 0)
    np.testing.assert_allclose(front, want, atol=1e-5)
    av.save(tmp_path / "a.npz")
    back = Avatar.load(tmp_path / "a.npz")
    np.testing.assert_array_equal(back.f_rest, av.f_rest)
    with pytest.raises(ValueError, match="not a whole degree"):
        Avatar(
            av.forest,
            av.d_mu,
            av.d_log_scale,
            av.d_rot,
            av.opacity_logit,
            av.f_dc,
            f_rest=np.zeros((av.num_gaussians, 4, 3)),
        )


def test_ply_carries_every_band_in_3dgs_order(tmp_path):
    plyfile = pytest.importorskip("plyfile")
    v, av = sh_avatar(degree=3)
    g = av.gaussians(v)
    g["sh_rest"] = av.f_rest
    write_ply(tmp_path / "sh.ply", g)
    el = plyfile.PlyData.read(str(tmp_path / "sh.ply"))["vertex"]
    names = [p.name for p in el.properties]
    assert names[6:9] == ["f_dc_0", "f_dc_1", "f_dc_2"] and names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54] == "opacity"
    np.testing.assert_allclose(el["f_rest_16"], av.f_rest[:, 1, 1], atol=1e-7)  # green, second coefficient
    np.testing.assert_allclose(read_ply(tmp_path / "sh.ply")["sh_rest"], av.f_rest, atol=1e-7)


def test_stream_takes_the_dc_colour_only_when_told(tmp_path):
    v, av = sh_avatar()
    with pytest.raises(ValueError, match="SH degree 2.*drop_sh"):
        write_stream(tmp_path / "s.pavs", av)
    assert not (tmp_path / "s.pavs").exists()
    info = write_stream(tmp_path / "s.pavs", av, quantize=False, drop_sh=True)
    back = read_stream(tmp_path / "s.pavs")
    assert back.sh_degree == 0 and back.meta["sh_degree_dropped"] == 2
    np.testing.assert_array_equal(back.f_dc, av.f_dc[info.order])


def test_training_with_sh_bands(tiny_dataset, tmp_path):
    from progressive_avatars.core.train.trainer import Trainer, config_for

    cfg = config_for(  # cumulative coarse levels: every trained face is in the PLY (backdrop: test_pipeline)
        "tiny",
        iterations=30,
        sh_degree=2,
        sh_every=10,
        checkpoint_every=15,
        eval_every=1000,
        coarse_stand_ins=False,
        coarse_backdrop=False,
    )
    tr = Trainer(tiny_dataset, str(tmp_path / "run"), cfg)
    tr.run(progress=False, stop_after=15)
    assert tr.model.active_sh_degree == 1
    resumed = Trainer(tiny_dataset, str(tmp_path / "run"), cfg, resume=True)
    resumed.run(progress=False)
    assert resumed.model.active_sh_degree == 2
    av = Avatar.load(tmp_path / "run" / "avatar.npz")
    assert av.sh_degree == 2 and np.all(np.isfinite(av.f_rest))
    assert np.abs(av.f_rest[:, :3]).max() > 1e-4  # the first band learned something
    assert np.abs(av.f_rest[:, 3:]).max() > 0  # the second band was active for its last iterations
    cfg_json = json.load(open(tmp_path / "run" / "config.json"))
    assert cfg_json["sh_degree"] == 2
    with pytest.raises(ValueError, match="SH degree 2.*configuration 0"):
        Trainer(tiny_dataset, str(tmp_path / "run"), config_for("tiny", iterations=30), resume=True)
    # export.py on the SH run: the stream needs --drop-sh (said clearly), the PLY then carries
    # every band of the trained avatar, in 3DGS order, readable by plyfile.
    import subprocess
    import sys

    from plyfile import PlyData

    from tests.test_pipeline import ENV, ROOT, run_script

    run = str(tmp_path / "run")
    args = ["--run", run, "--stream", str(tmp_path / "s.pavs"), "--ply", str(tmp_path / "f.ply"), "--max-views", "4"]
    refused = subprocess.run(
        [sys.executable, f"{ROOT}/scripts/export.py", *args], capture_output=True, text=True, timeout=600, env=ENV
    )
    assert refused.returncode == 2 and "--drop-sh" in refused.stderr and not (tmp_path / "s.pavs").exists()
    res = run_script("export.py", *args, "--drop-sh")
    assert res["ply_gaussians"] == av.num_gaussians
    vert = PlyData.read(str(tmp_path / "f.ply"))["vertex"]
    K = av.f_rest.shape[1]
    assert K == 8 and [n for n in vert.data.dtype.names if n.startswith("f_rest_")] == [
        f"f_rest_{j}" for j in range(3 * K)
    ]
    rest = np.stack([np.stack([vert[f"f_rest_{c * K + k}"] for c in range(3)], 1) for k in range(K)], 1)

    # Same rows as the trained avatar's bands, in stream order (compare as sorted row sets).
    def rows(a):
        a = a.reshape(len(a), -1)
        return a[np.lexsort(a.T[::-1])]

    np.testing.assert_array_equal(rows(rest), rows(av.f_rest))
    np.testing.assert_array_equal(read_ply(tmp_path / "f.ply")["sh_rest"], rest)
    # A prefix (version 5 interleaves the template faces with deeper ones): each PLY row's bands
    # and colour are those of the face the stream's prefix holds there.
    part_args = [*args[:4], "--ply", str(tmp_path / "p.ply"), *args[6:], "--budget", "40", "--drop-sh"]
    res = run_script("export.py", *part_args)
    part = read_stream(tmp_path / "s.pavs", percent=40)
    assert res["ply_gaussians"] == part.num_gaussians < av.num_gaussians
    got = read_ply(tmp_path / "p.ply")
    np.testing.assert_allclose(got["colors"], sh_to_rgb(part.f_dc), atol=0.01)  # the stream quantises colour


# The real spherical harmonics with the Condon-Shortley phase, m = -l..l, in Cartesian form on
# the unit sphere, their constants written from their closed forms (not sh.py's decimals).
PI = np.pi
C0 = 1 / (2 * np.sqrt(PI))
C1 = np.sqrt(3 / (4 * PI))
C2 = [np.sqrt(15 / PI) / 2, -np.sqrt(15 / PI) / 2, np.sqrt(5 / PI) / 4, -np.sqrt(15 / PI) / 2, np.sqrt(15 / PI) / 4]
C3 = [
    -np.sqrt(35 / (2 * PI)) / 4,
    np.sqrt(105 / PI) / 2,
    -np.sqrt(21 / (2 * PI)) / 4,
    np.sqrt(7 / PI) / 4,
    -np.sqrt(21 / (2 * PI)) / 4,
    np.sqrt(105 / PI) / 4,
    -np.sqrt(35 / (2 * PI)) / 4,
]


def real_sh(deg, d):
    """The basis [N, (deg+1)^2] at unit directions d [N,3]."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    xx, yy, zz = x * x, y * y, z * z
    Y = [np.full_like(x, C0)]
    if deg > 0:
        Y += [-C1 * y, C1 * z, -C1 * x]
    if deg > 1:
        Y += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if deg > 2:
        Y += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return np.stack(Y, 1)


def eval_sh_reference(deg, coeffs, d):
    """coeffs [N,3,16] (channel, coefficient)."""
    Y = real_sh(deg, d)
    return np.einsum("nk,nck->nc", Y, coeffs[:, :, : Y.shape[1]])


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_rgb_matches_the_real_harmonics_coefficient_by_coefficient(degree):
    rng = np.random.default_rng(7)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    k = sh.num_rest(degree)
    for j in range(k):  # one coefficient at a time: a wrong sign or slot shows on its own
        dc = rng.normal(size=(64, 3))
        rest = np.zeros((64, k, 3))
        rest[:, j, :] = rng.normal(size=(64, 3))
        coeffs = np.concatenate([dc[:, :, None], rest.transpose(0, 2, 1)], 2)  # [N,3,1+k]
        coeffs = np.concatenate([coeffs, np.zeros((64, 3, 16 - coeffs.shape[2]))], 2)
        want = eval_sh_reference(degree, coeffs, d) + 0.5
        np.testing.assert_allclose(sh.sh_rgb(dc, rest, d, np.stack), want, atol=1e-12, err_msg=f"coefficient {j}")


def test_basis_values_along_plus_y_by_hand():
    # d = +y: x = z = 0, y = 1.
    got = sh.rest_basis(np.array([[0.0, 1.0, 0.0]]), 3, np.stack)[0]
    want = np.zeros(15)
    want[0] = -C1  # -C1·y
    want[5] = -C2[2]  # C2[2]·(2zz - xx - yy) = -C2[2]
    want[7] = -C2[4]  # C2[4]·(xx - yy) = -C2[4]
    want[8] = -C3[0]  # C3[0]·y·(3xx - yy) = -C3[0]
    want[10] = -C3[2]  # C3[2]·y·(4zz - xx - yy) = -C3[2]
    np.testing.assert_allclose(got, want, atol=1e-15)


def test_basis_xyz_term_sign_by_hand():
    d = np.array([[1.0, 1.0, 1.0]]) / np.sqrt(3.0)
    got = sh.rest_basis(d, 3, np.stack)[0]
    assert got[9] == pytest.approx(C3[1] / 3.0**1.5, rel=1e-12)  # C3[1]·x·y·z
    assert got[11] == pytest.approx(C3[3] * (1 / 3**0.5) * (2 / 3 - 2.0), rel=1e-12)  # C3[3]·z·(2zz-3xx-3yy)


def test_degree_above_the_stored_coefficients_uses_what_is_there():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(10, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dc, rest = rng.normal(size=(10, 3)), rng.normal(size=(10, 3, 3))
    got = sh.sh_rgb(dc, rest, d, np.stack, degree=3)  # asks for 15, only 3 stored
    x, y, z = d[:, :1], d[:, 1:2], d[:, 2:]
    want = 0.5 + C0 * dc - C1 * y * rest[:, 0] + C1 * z * rest[:, 1] - C1 * x * rest[:, 2]
    np.testing.assert_allclose(got, want, atol=1e-12)
