"""3DGS PLY import/export in a Blender that has nothing but Blender.

The add-on runs under the bpy module in a subprocess (own BLENDER_USER_* folders, as in
test_blender_extension) with plyfile, trimesh, PIL, scipy, torch and numba made
unimportable, so any stray import of them fails here. The PLY is written by core (3DGS
layout with one SH band), read back after export by plyfile in this process (a third-party
reader).
"""

import os

import numpy as np
import pytest

from tests.test_blender_extension import _bpy_dir, run_scenario

pytestmark = pytest.mark.blender

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BLOCKED = ("plyfile", "trimesh", "PIL", "scipy", "torch", "numba")


SCENARIO = os.path.join(ROOT, "tests", "blender_scenarios", "ply_import.py")  # run in place: it imports stock_blender


def _gaussians(n, rng):
    """Trained-splat proportions: flat ellipsoids of a few mm on a ~10 cm blob, mostly opaque,
    some near-transparent, one SH band (K = 3 coefficients per channel)."""
    d = rng.normal(size=(n, 3))
    means = 0.1 * d / np.linalg.norm(d, axis=1, keepdims=True) + rng.normal(0, 0.003, (n, 3))
    scales = np.exp(rng.normal(np.log(0.004), 0.6, (n, 3)))
    scales[:, 2] *= 0.1
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    opac = 1 / (1 + np.exp(-rng.normal(2.0, 2.0, n)))
    colors = np.clip(rng.normal(0.5, 0.25, (n, 3)), 0.01, 1.2)
    return {
        "means": means,
        "quats": q,
        "scales": scales,
        "opacities": opac,
        "colors": colors,
        "sh_rest": rng.normal(0, 0.05, (n, 3, 3)),
    }


def _foreign_copies(src, out):
    """The same splats as ASCII and as big-endian PLYs (other tools write them)."""
    plyfile = pytest.importorskip("plyfile")
    v = plyfile.PlyData.read(src)["vertex"].data
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")], text=True).write(os.path.join(out, "splats_ascii.ply"))
    big = v.astype(v.dtype.newbyteorder(">"))
    plyfile.PlyData([plyfile.PlyElement.describe(big, "vertex")], byte_order=">").write(
        os.path.join(out, "splats_big_endian.ply")
    )


@pytest.fixture(scope="module")
def ply_session(tmp_path_factory):
    _bpy_dir()
    from progressive_avatars.core.io.ply import write_ply

    tmp = str(tmp_path_factory.mktemp("blender_ply"))
    out = os.path.join(tmp, "out")
    os.makedirs(out)
    g = _gaussians(3000, np.random.default_rng(5))
    # Dark DC coefficients below -0.5/C0 (a colour clamped at 0 before the bands add): kept as such
    g["f_dc"] = (np.asarray(g["colors"]) - 0.5) / 0.28209479177387814
    g["f_dc"][::7] = -2.8
    src = os.path.join(out, "splats.ply")
    write_ply(src, g)
    _foreign_copies(src, out)
    rep, _ = run_scenario(SCENARIO, [ROOT, src, out, ",".join(BLOCKED)], "PA_PLY", tmp)
    assert not rep["errors"], rep["errors"][0]
    return {"rep": rep, "arrays": dict(np.load(os.path.join(out, "arrays.npz"))), "out": out, "src": src}


def _plyfile(path):
    plyfile = pytest.importorskip("plyfile")
    return plyfile.PlyData.read(path)["vertex"].data


def test_nothing_but_blender_was_imported(ply_session):
    assert ply_session["rep"]["blocked_loaded"] == []


def test_import_keeps_positions_and_ranks_by_importance(ply_session):
    from progressive_avatars.core.io import ply

    rep, arr = ply_session["rep"], ply_session["arrays"]
    g = ply.read_ply(ply_session["src"])
    assert rep["import"] == ["FINISHED"] and rep["total"] == 3000 and rep["bands"] == 3
    np.testing.assert_array_equal(arr["position"], g["means"])
    order = np.argsort(arr["rank"])
    np.testing.assert_array_equal(order, ply.importance_order(g))
    key = g["opacities"].astype(np.float64) * np.prod(g["scales"].astype(np.float64), axis=1)
    assert np.all(np.diff(key[order]) <= 1e-12 * key.max())  # most opaque x largest first
    np.testing.assert_array_equal(arr["rank_file"], np.arange(3000))
    # Colours: the DC colour, stored linear (Blender colour attributes are scene-linear).
    from progressive_avatars.core.bridge.splats import srgb_to_linear

    np.testing.assert_allclose(arr["color"][:, :3], srgb_to_linear(g["colors"]), atol=1e-6)


def test_budget_slider_sets_count_modifier_and_size(ply_session):
    from progressive_avatars.core.io.ply import splat_ply_bytes

    rep = ply_session["rep"]
    assert rep["count_40"] == 1200 and rep["modifier_count"] == 1200
    assert rep["instances"] == 1200  # Geometry Nodes drew exactly the budget's splats
    assert rep["mb_40"] == pytest.approx(splat_ply_bytes(1200, 3) / 1e6)
    assert rep["count_0"] == 0


def test_export_writes_the_budget_in_rank_order_readable_by_plyfile(ply_session):
    from progressive_avatars.core.io import ply

    rep, out = ply_session["rep"], ply_session["out"]
    assert rep["export"] == ["FINISHED"] and rep["export_world"] == ["FINISHED"]
    src = _plyfile(ply_session["src"])
    got = _plyfile(os.path.join(out, "export_40.ply"))
    assert len(got) == 1200
    keep = ply.importance_order(ply.read_ply(ply_session["src"]))[:1200]
    for name in src.dtype.names:
        if name in ("nx", "ny", "nz"):
            continue
        tol = 2e-4 if name == "opacity" else 1e-5  # logit through float32 sigmoid
        np.testing.assert_allclose(got[name], src[name][keep], atol=tol, rtol=1e-5, err_msg=name)
    # World space: the importer stood the Y-up file up in Z-up Blender (x, y, z) -> (x, -z, y),
    # then the object was moved by (1, 2, 3)
    world = _plyfile(os.path.join(out, "export_40_world.ply"))
    np.testing.assert_allclose(world["x"] - 1.0, got["x"], atol=1e-6)
    np.testing.assert_allclose(world["y"] - 2.0, -got["z"], atol=1e-6)
    np.testing.assert_allclose(world["z"] - 3.0, got["y"], atol=1e-6)
    # ... and every splat turned with it: world rotation = q_x(+90 degrees) * local rotation, same scales
    from progressive_avatars.core.geometry.rotations import quat_multiply

    def quats(a):
        q = np.stack([a[f"rot_{k}"] for k in range(4)], 1).astype(np.float64)
        return q / np.linalg.norm(q, axis=1, keepdims=True)

    turn = np.array([np.sqrt(0.5), np.sqrt(0.5), 0.0, 0.0])
    want = quat_multiply(np.broadcast_to(turn, (len(got), 4)), quats(got))
    np.testing.assert_allclose(np.abs(np.sum(quats(world) * want, axis=1)), 1.0, atol=1e-5)
    for k in range(3):
        np.testing.assert_allclose(world[f"scale_{k}"], got[f"scale_{k}"], atol=1e-5)


def test_ascii_and_big_endian_plys_import_in_a_stock_blender(ply_session):
    rep, arr = ply_session["rep"], ply_session["arrays"]
    for name in ("splats_ascii", "splats_big_endian"):
        assert rep[f"import_{name}"] == ["FINISHED"], rep[f"import_{name}"]
        np.testing.assert_allclose(arr[f"position_{name}"], arr["position"], atol=1e-6)
    assert rep["z_up"] and rep["z_up_off_identity"]


def test_broken_file_is_named_and_leaves_the_scene_as_it_was(ply_session):
    rep = ply_session["rep"]
    assert "bad.ply" in rep["bad_message"] and "missing vertex properties" in rep["bad_message"]
    assert rep["bad_left_scene"]
