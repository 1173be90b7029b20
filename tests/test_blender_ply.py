"""3DGS PLY import/export in a Blender that has nothing but Blender.

The add-on runs under the bpy module in a subprocess (own BLENDER_USER_* folders, as in
test_blender_extension) with plyfile, trimesh, PIL, scipy, torch and numba made
unimportable, so any stray import of them fails here. The PLY is written by core (3DGS
layout with one SH band), read back after export by plyfile in this process (a third-party
reader).
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.test_blender_extension import _bpy_dir, _clean_env

pytestmark = pytest.mark.blender

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BLOCKED = ("plyfile", "trimesh", "PIL", "scipy", "torch", "numba")

CHILD = r'''
import importlib.util, json, os, sys, traceback
root, ply_path, out, blocked = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4].split(",")


class Block:
    """A stock Blender has none of these: importing one must fail, as it would there."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in blocked:
            raise ImportError(f"{name} is blocked (not in a stock Blender)")
        return None


sys.meta_path.insert(0, Block())
import bpy
import numpy as np

spec = importlib.util.spec_from_file_location("pa_blk", os.path.join(root, "__init__.py"),
                                              submodule_search_locations=[root])
pkg = importlib.util.module_from_spec(spec); sys.modules["pa_blk"] = pkg; spec.loader.exec_module(pkg)
pkg.register()
R = {"errors": []}
A = {}
try:
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    res = bpy.ops.import_scene.progressive_avatars_splat_ply(filepath=ply_path, order="IMPORTANCE")
    obj = bpy.context.active_object
    R["import"] = list(res)
    st = obj.pa_avatar
    R["total"], R["bands"] = st.total, int(obj["pa_sh_bands"])
    me = obj.data
    def read(name, width, dtype=np.float32, field="value"):
        a = np.empty(len(me.vertices) * width, dtype); me.attributes[name].data.foreach_get(field, a)
        return a.reshape(-1, width) if width > 1 else a
    A["position"] = read("position", 3, field="vector")
    A["rank"] = read("rank", 1, np.int32)
    A["color"] = read("color", 4, field="color")
    st.budget = 40.0
    R["count_40"], R["mb_40"] = st.count, st.megabytes
    mod = obj.modifiers["PA Splats"]
    ng = mod.node_group
    key = next(i.identifier for i in ng.interface.items_tree if getattr(i, "name", "") == "Count" and i.in_out == "INPUT")
    R["modifier_count"] = mod[key]
    dg = bpy.context.evaluated_depsgraph_get()
    R["instances"] = sum(1 for inst in dg.object_instances if inst.is_instance and inst.parent
                         and inst.parent.original == obj)
    exp = os.path.join(out, "export_40.ply")
    R["export"] = list(bpy.ops.export_scene.progressive_avatars_ply(filepath=exp, world_space=False))
    obj.location = (1.0, 2.0, 3.0)
    bpy.context.view_layer.update()
    expw = os.path.join(out, "export_40_world.ply")
    R["export_world"] = list(bpy.ops.export_scene.progressive_avatars_ply(filepath=expw, world_space=True))
    res2 = bpy.ops.import_scene.progressive_avatars_splat_ply(filepath=ply_path, order="FILE")
    o2 = bpy.context.active_object
    rk = np.empty(len(o2.data.vertices), np.int32); o2.data.attributes["rank"].data.foreach_get("value", rk)
    A["rank_file"] = rk
    o2.pa_avatar.budget = 0.0
    R["count_0"] = o2.pa_avatar.count
    # A broken file: a clear message naming it, and nothing added to the scene.
    bad = os.path.join(out, "bad.ply")
    with open(bad, "wb") as fh:
        fh.write(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n2\n3\n")
    n_before = len(bpy.data.objects), len(bpy.data.meshes)
    try:
        R["bad"] = list(bpy.ops.import_scene.progressive_avatars_splat_ply(filepath=bad))
    except RuntimeError as exc:
        R["bad_message"] = str(exc)
    R["bad_left_scene"] = (len(bpy.data.objects), len(bpy.data.meshes)) == n_before
    R["blocked_loaded"] = sorted(m for m in sys.modules if m.split(".")[0] in blocked)
except Exception:
    R["errors"].append(traceback.format_exc())
np.savez(os.path.join(out, "arrays.npz"), **A)
print("PA_PLY " + json.dumps(R))
'''


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
    return {"means": means, "quats": q, "scales": scales, "opacities": opac, "colors": colors,
            "sh_rest": rng.normal(0, 0.05, (n, 3, 3))}


@pytest.fixture(scope="module")
def ply_session(tmp_path_factory):
    _bpy_dir()
    from progressive_avatars.core.io.ply import write_ply

    tmp = str(tmp_path_factory.mktemp("blender_ply"))
    out = os.path.join(tmp, "out")
    os.makedirs(out)
    g = _gaussians(3000, np.random.default_rng(5))
    src = os.path.join(out, "splats.ply")
    write_ply(src, g)
    script = os.path.join(tmp, "child.py")
    with open(script, "w") as fh:
        fh.write(CHILD)
    proc = subprocess.run([sys.executable, script, ROOT, src, out, ",".join(BLOCKED)], capture_output=True, text=True,
                          env=_clean_env(tmp), timeout=300)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PA_PLY ")]
    if not lines:
        pytest.fail("Blender session produced no report:\n" + proc.stdout[-3000:] + proc.stderr[-3000:])
    rep = json.loads(lines[-1][len("PA_PLY "):])
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
    from progressive_avatars.core.bridge.preview import srgb_to_linear

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
    world = _plyfile(os.path.join(out, "export_40_world.ply"))
    np.testing.assert_allclose(world["x"] - 1.0, got["x"], atol=1e-6)
    np.testing.assert_allclose(world["z"] - 3.0, got["z"], atol=1e-6)


def test_broken_file_is_named_and_leaves_the_scene_as_it_was(ply_session):
    rep = ply_session["rep"]
    assert "bad.ply" in rep["bad_message"] and "binary little-endian" in rep["bad_message"]
    assert rep["bad_left_scene"]
