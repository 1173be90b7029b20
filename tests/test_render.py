"""The differentiable rasteriser (core/render/rasterize.py) against the dense float64 reference
(core/render/reference.py), finite differences, and itself (contrib, means2d, depth)."""

import math

import numpy as np
import pytest
import torch

from progressive_avatars.core.render.reference import render_reference  # noqa: E402

from progressive_avatars.core.geometry.camera import Camera  # noqa: E402
from progressive_avatars.core.render.rasterize import RenderOutput, render, render_levels, render_numpy  # noqa: E402

W, H = 40, 36  # not multiples of 16: partial tiles on both axes


def make_camera():
    # Slightly rotated, fx != fy, principal point off-centre: intrinsics must all be honoured.
    a = 0.07
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    R = R @ np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.05), -np.sin(0.05)], [0.0, np.sin(0.05), np.cos(0.05)]])
    return Camera(R, np.array([0.03, -0.02, 0.1]), 46.0, 39.0, 17.3, 20.6, W, H)


def world_from_camera(cam, pc):
    return (np.asarray(pc) - cam.t) @ cam.R  # inverse of R p + t


def make_scene(seed=0, n=48, dtype=torch.float64, special=True):
    """Random Gaussians in front of the camera, plus the awkward cases."""
    rng = np.random.default_rng(seed)
    cam = make_camera()
    z = rng.uniform(0.8, 3.0, n)
    xn = rng.uniform(-0.45, 0.5, n)
    yn = rng.uniform(-0.55, 0.45, n)
    pc = np.stack([xn * z, yn * z, z], 1)
    scales = rng.uniform(0.015, 0.09, (n, 3)) * z[:, None] * 0.6
    opac = rng.uniform(0.15, 0.9, n)
    if special:
        extra_pc, extra_s, extra_o = [], [], []

        def add(p, s, o):
            extra_pc.append(p), extra_s.append(s), extra_o.append(o)

        add([0.0, 0.0, -0.5], [0.1, 0.1, 0.1], 0.8)  # behind the camera
        add([0.001, 0.0, 0.0095], [0.004, 0.004, 0.004], 0.5)  # just in front of the near plane: culled
        add([0.0005, -0.0004, 0.0108], [0.004, 0.003, 0.005], 0.2)  # just behind it: huge on screen
        add([(16.0 - 17.3) / 46.0 * 1.5, (16.0 - 20.6) / 39.0 * 1.5, 1.5], [0.04, 0.05, 0.03], 0.7)  # tile corner
        add([0.1, 0.05, 1.2], [0.08, 0.06, 1e-6], 0.8)  # flat
        add([-0.2, 0.1, 1.1], [1e-6, 0.07, 0.05], 0.6)  # flat, other axis
        add([0.3, -0.2, 4.0], [6.0, 5.0, 7.0], 0.25)  # huge
        add([1.6 * 2.0, 0.1, 2.0], [0.9, 0.7, 0.5], 0.6)  # centre outside the clamped FOV, tail visible
        add([30.0, 0.0, 2.0], [0.05, 0.05, 0.05], 0.9)  # far outside the frustum
        pc = np.concatenate([pc, np.array(extra_pc)])
        scales = np.concatenate([scales, np.array(extra_s)])
        opac = np.concatenate([opac, np.array(extra_o)])
    m = len(pc)
    means = world_from_camera(cam, pc)
    quats = rng.normal(size=(m, 4))
    colors = rng.uniform(0.0, 1.0, (m, 3))
    bg = np.array([0.2, 0.5, 0.1])
    t = [torch.tensor(x, dtype=dtype) for x in (means, quats, scales, opac, colors, bg)]
    return cam, t


def loss_weights(seed, n_ch=3, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(H, W, n_ch, generator=g, dtype=dtype), torch.randn(H, W, generator=g, dtype=dtype))


def rel_err(a, b):
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30))


def leaves(params, dtype=None):
    return [p.detach().clone().to(dtype or p.dtype).requires_grad_(True) for p in params]


NAMES = ["means", "quats", "scales", "opacities", "colors", "background"]


def assert_matches_reference(params, cam, wi, wa, image_tol, grad_tol, contrib_tol=None):
    """Our render of ``params`` against the dense float64 reference: image (and contrib) within
    the absolute tolerances, every gradient of sum(image * wi) + sum(alpha * wa) within grad_tol
    relative. Returns our RenderOutput."""
    ours = leaves(params)
    out = render(*ours[:5], cam, ours[5])
    ((out.image * wi).sum() + (out.alpha * wa).sum()).backward()
    ref = leaves(params)
    img, alpha, contrib = render_reference(*ref[:5], cam, ref[5])
    assert float((out.image - img).detach().abs().max()) <= image_tol
    if contrib_tol is not None:
        assert torch.allclose(out.contrib, contrib, atol=contrib_tol)
    ((img * wi).sum() + (alpha * wa).sum()).backward()
    for name, a, b in zip(NAMES, ours, ref):
        assert rel_err(a.grad, b.grad) <= grad_tol, name
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_matches_reference(dtype):
    cam, params = make_scene(0, dtype=dtype)
    out = render(*params[:5], cam, params[5])
    assert isinstance(out, RenderOutput)
    assert out.image.shape == (H, W, 3) and out.image.dtype == dtype
    assert out.alpha.shape == (H, W) and out.contrib.shape == (len(params[0]),)
    ref_img, ref_alpha, ref_contrib = render_reference(*[p.double() for p in params[:5]], cam, params[5].double())
    assert float((out.image.double() - ref_img).abs().max()) <= 1e-4
    assert float((out.alpha.double() - ref_alpha).abs().max()) <= 1e-4
    assert torch.allclose(out.contrib.double(), ref_contrib, rtol=1e-4, atol=1e-4)
    assert torch.isfinite(out.image).all()
    # The scene really exercises the special cases.
    radii = out.radii.numpy()
    n = len(radii) - 9
    assert radii[n] == 0 and radii[n + 1] == 0 and radii[n + 8] == 0  # behind, before near, outside
    assert radii[n + 2] > 20 and radii[n + 6] > 20  # near-plane and huge Gaussians cover the image
    assert (radii[:n] > 0).sum() > n // 2


def test_float32_render_is_the_float64_render_rounded_once():
    """The kernels composite in float64 whatever the input and write a float32 render's image
    directly in float32: the same values as a float64 render of the same inputs, rounded once
    (every level of a render_levels pass, and render_numpy, too)."""
    cam, params = make_scene(2, dtype=torch.float32)
    out32 = render(*params[:5], cam, params[5])
    out64 = render(*[p.double() for p in params[:5]], cam, params[5].double())
    assert out32.image.dtype == torch.float32 and out32.alpha.dtype == torch.float32
    assert torch.equal(out32.image, out64.image.float()) and torch.equal(out32.alpha, out64.alpha.float())
    level = np.arange(len(params[0])) % 3
    lv32 = render_levels(*params[:5], cam, params[5], level=level, upto=[0, 2])
    lv64 = render_levels(*[p.double() for p in params[:5]], cam, params[5].double(), level=level, upto=[0, 2])
    for a, b in zip(lv32, lv64):
        assert torch.equal(a.image, b.image.float()) and torch.equal(a.alpha, b.alpha.float())
    img, alpha, _ = render_numpy(*[p.numpy() for p in params[:5]], cam, params[5].numpy())
    assert img.dtype == np.float32 and np.array_equal(img, out32.image.numpy())
    assert alpha.dtype == np.float32 and np.array_equal(alpha, out32.alpha.numpy())
    frozen = [p.numpy().copy() for p in params[:5]]
    for a in frozen:
        a.flags.writeable = False  # read-only arrays (np.frombuffer, memory maps) take the copies
    assert np.array_equal(render_numpy(*frozen, cam, params[5].numpy())[0], img)


def test_each_gradient_comes_back_in_its_own_inputs_precision():
    """Mixed precision: float32 means beside float64 opacities and colours. The float64 inputs'
    gradients are the float64 kernels' values, not rounded through the means' float32: equal bit
    for bit to an all-float64 render of the same values."""
    cam, params = make_scene(4, dtype=torch.float64)
    means32 = params[0].float()
    # loss weights that float32 holds exactly: the float32 image's incoming gradient is then exact too
    wi, wa = (w.float().double() for w in loss_weights(5))
    grads = []
    for means in (means32, means32.double()):
        ps = [means.clone().requires_grad_(True)] + [p.clone().requires_grad_(True) for p in params[1:5]]
        out = render(*ps, cam, params[5])
        ((out.image.double() * wi).sum() + (out.alpha.double() * wa).sum()).backward()
        grads.append([p.grad for p in ps])
    mixed, full = grads
    assert mixed[0].dtype == torch.float32 and mixed[3].dtype == torch.float64 and mixed[4].dtype == torch.float64
    assert torch.equal(mixed[3], full[3]) and torch.equal(mixed[4], full[4])
    assert torch.equal(mixed[0], full[0].float())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_match_reference_autograd(dtype):
    cam, params = make_scene(1, dtype=dtype)
    wi, wa = loss_weights(3, dtype=dtype)
    ours = leaves(params)
    out = render(*ours[:5], cam, ours[5])
    ((out.image * wi).sum() + (out.alpha * wa).sum()).backward()

    ref = leaves(params, torch.float64)
    m2d = torch.zeros(len(params[0]), 2, dtype=torch.float64, requires_grad=True)
    img, alpha, _ = render_reference(*ref[:5], cam, ref[5], means2d=m2d)
    ((img * wi.double()).sum() + (alpha * wa.double()).sum()).backward()
    for name, a, b in zip(NAMES, ours, ref):
        assert a.grad is not None and torch.isfinite(a.grad).all(), name
        assert rel_err(a.grad, b.grad) <= 1e-3, (name, rel_err(a.grad, b.grad))
    assert out.means2d.grad is not None
    assert rel_err(out.means2d.grad, m2d.grad) <= 1e-3


@pytest.mark.parametrize("seed, size", [(10, (40, 36)), (11, (17, 50)), (12, (33, 16)), (13, (64, 9))])
def test_random_scenes_match_reference(seed, size):
    # Other image shapes (single tile rows/columns, partial tiles) and denser scenes.
    cam, params = make_scene(seed, n=80)
    w, h = size
    cam = Camera(cam.R, cam.t, cam.fx * w / W, cam.fy * h / H, cam.cx * w / W + 0.37, cam.cy * h / H - 0.21, w, h)
    g = torch.Generator().manual_seed(seed)
    wi, wa = torch.randn(h, w, 3, generator=g, dtype=torch.float64), torch.randn(h, w, generator=g, dtype=torch.float64)
    ours = leaves(params)
    out = render(*ours[:5], cam, ours[5])
    ((out.image * wi).sum() + (out.alpha * wa).sum()).backward()
    ref = leaves(params)
    img, alpha, contrib = render_reference(*ref[:5], cam, ref[5])
    assert float((out.image - img).detach().abs().max()) <= 1e-10
    assert torch.allclose(out.contrib, contrib, atol=1e-10)
    ((img * wi).sum() + (alpha * wa).sum()).backward()
    for name, a, b in zip(NAMES, ours, ref):
        assert rel_err(a.grad, b.grad) <= 1e-6, name


def test_gradients_match_finite_differences():
    cam, params = make_scene(2, n=24)
    wi, wa = loss_weights(5)
    ours = leaves(params)
    out = render(*ours[:5], cam, ours[5])
    ((out.image * wi).sum() + (out.alpha * wa).sum()).backward()

    rng = np.random.default_rng(0)
    for k, name in enumerate(NAMES[:5]):
        analytic, numeric = [], []
        flat = params[k].reshape(-1)
        for idx in rng.choice(flat.numel(), size=min(24, flat.numel()), replace=False):
            h = 1e-6 * max(abs(float(flat[idx])), 1e-3)  # relative step: some scales are 1e-6
            vals = []
            for sign in (1.0, -1.0):
                ps = [p.clone() for p in params]
                ps[k].view(-1)[idx] += sign * h
                img, alpha = _forward64(ps, cam)
                vals.append(float((img * wi).sum() + (alpha * wa).sum()))
            numeric.append((vals[0] - vals[1]) / (2 * h))
            analytic.append(float(ours[k].grad.reshape(-1)[idx]))
        err = np.linalg.norm(np.subtract(analytic, numeric)) / max(np.linalg.norm(numeric), 1e-30)
        assert err <= 1e-3, (name, err)


def _forward64(ps, cam):
    with torch.no_grad():
        out = render(*ps[:5], cam, ps[5])
    return out.image.double(), out.alpha.double()


def test_early_termination_matches_reference():
    # Many nearly opaque layers over a patch: pixels reach T < 1e-4 and stop.
    rng = np.random.default_rng(4)
    cam = make_camera()
    n = 40
    z = np.linspace(1.0, 2.0, n)
    pc = np.stack([rng.uniform(-0.05, 0.05, n) * z, rng.uniform(-0.05, 0.05, n) * z, z], 1)
    params = [
        torch.tensor(x)
        for x in (
            world_from_camera(cam, pc),
            rng.normal(size=(n, 4)),
            rng.uniform(0.1, 0.2, (n, 3)) * z[:, None],
            rng.uniform(0.6, 0.95, n),
            rng.uniform(0, 1, (n, 3)),
            np.array([0.3, 0.3, 0.3]),
        )
    ]
    out = assert_matches_reference(params, cam, *loss_weights(7), image_tol=1e-4, grad_tol=1e-3)
    assert float(out.alpha.detach().max()) > 1 - 1e-3  # the stop rule is exercised


def test_box_and_chord_walks_match_reference():
    # Thin splats facing the camera, turned about the view axis from axis-aligned to diagonal:
    # the forward walks the near-axis-aligned ones by their pixel box and the tilted ones by
    # chords (kernels.CHORD_RHO2); both must composite exactly the dense reference's pixels.
    from progressive_avatars.core.geometry.rotations import rotmat_to_quat
    from progressive_avatars.core.render import kernels as rk

    rng = np.random.default_rng(21)
    cam = make_camera()
    n = 60
    z = rng.uniform(1.0, 2.0, n)
    pc = np.stack([rng.uniform(-0.4, 0.4, n) * z, rng.uniform(-0.45, 0.4, n) * z, z], 1)
    turn = np.linspace(0.0, np.pi, n)
    quats = []
    for a in turn:
        rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        quats.append(rotmat_to_quat(cam.R.T @ rz))  # camera-frame rotation about the view axis
    long = rng.uniform(0.02, 0.25, n) * z  # ~1 to ~11 px standard deviation along the long axis
    scales = np.stack([long, long / rng.uniform(3.0, 10.0, n), np.full(n, 1e-5)], 1)
    params = [
        torch.tensor(x)
        for x in (
            world_from_camera(cam, pc),
            np.array(quats),
            scales,
            rng.uniform(0.3, 0.95, n),
            rng.uniform(0, 1, (n, 3)),
            np.array([0.2, 0.5, 0.1]),
        )
    ]
    conic = rk.project_forward(
        *[np.ascontiguousarray(p.numpy()) for p in params[:4]],
        np.ascontiguousarray(cam.R, np.float64), np.ascontiguousarray(cam.t, np.float64),
        cam.fx, cam.fy, cam.cx, cam.cy, rk.fov_limits(W, H, cam.fx, cam.fy, cam.cx, cam.cy), W, H, 0.01, 0.3,
    )[1]  # fmt: skip
    rho2 = conic[:, 1] ** 2 / (conic[:, 0] * conic[:, 2])
    assert (rho2 <= rk.CHORD_RHO2).sum() >= 10 and (rho2 > rk.CHORD_RHO2).sum() >= 10  # both walks
    assert_matches_reference(params, cam, *loss_weights(5), image_tol=1e-10, grad_tol=1e-6, contrib_tol=1e-10)


def test_contrib_is_gradient_of_image_wrt_constant_colour():
    cam, params = make_scene(3)
    probe = torch.zeros(len(params[0]), 1, dtype=torch.float64, requires_grad=True)
    out = render(*params[:4], probe, cam)
    out.image.sum().backward()
    # The forward sums alpha*T in float64; the backward replays 1 - alpha rounded to float32.
    assert torch.allclose(out.contrib, probe.grad[:, 0], rtol=1e-6, atol=1e-9)
    assert not out.contrib.requires_grad
    assert float(out.contrib.sum()) > 0
    culled = out.radii == 0
    assert torch.all(out.contrib[culled] == 0)


def test_depth_matches_reference():
    cam, params = make_scene(5)
    ours = leaves(params)
    out = render(*ours[:5], cam, ours[5], return_depth=True)
    assert out.depth.shape == (H, W)
    wd = loss_weights(9)[1]
    (out.depth * wd).sum().backward()

    ref = leaves(params)
    z = ref[0] @ torch.as_tensor(cam.R).T[:, 2] + float(cam.t[2])
    img, alpha, _ = render_reference(ref[0], ref[1], ref[2], ref[3], z[:, None], cam)
    depth = torch.where(alpha > 1e-10, img[..., 0] / alpha.clamp_min(1e-10), torch.zeros_like(alpha))
    assert float((out.depth - depth).detach().abs().max()) <= 1e-6
    (depth * wd).sum().backward()
    for name, a, b in zip(NAMES[:4], ours, ref):
        assert rel_err(a.grad, b.grad) <= 1e-3, name


def test_render_numpy_and_partial_requires_grad():
    cam, params = make_scene(6, dtype=torch.float32)
    img, alpha, contrib = render_numpy(*[p.numpy() for p in params[:5]], cam, params[5].numpy())
    out = render(*params[:5], cam, params[5])
    assert img.dtype == np.float32 and np.abs(img - out.image.numpy()).max() < 1e-6
    assert np.abs(alpha - out.alpha.numpy()).max() < 1e-6
    assert np.allclose(contrib, out.contrib.numpy(), atol=1e-5)
    # Only colours require grad: the others get none, nothing breaks.
    colors = params[4].clone().requires_grad_(True)
    out = render(*params[:4], colors, cam)
    out.image.sum().backward()
    assert colors.grad is not None and params[0].grad is None


def test_empty_and_degenerate_scenes_are_finite():
    cam = make_camera()
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    bg = torch.tensor([0.1, 0.2, 0.3])
    out = render(*empty, cam, bg)
    assert torch.allclose(out.image, bg.expand(H, W, 3)) and float(out.alpha.abs().max()) == 0
    # Everything culled or extreme still gives finite values and gradients.
    cam, params = make_scene(8, n=4)
    ps = leaves(params)
    with torch.no_grad():
        ps[2][:] = torch.tensor([1e-7, 1e-7, 1e-7], dtype=torch.float64)
        ps[2][0] = torch.tensor([1e4, 1e4, 1e-9], dtype=torch.float64)
    out = render(*ps[:5], cam, ps[5])
    (out.image.sum() + out.alpha.sum()).backward()
    for p in ps:
        assert torch.isfinite(p.grad).all()


def test_backend_auto_falls_back_to_cpu_without_cuda():
    cam, params = make_scene(0, n=5, special=False)
    a = render(*params[:5], cam, params[5], backend="auto").image
    b = render(*params[:5], cam, params[5], backend="cpu").image
    assert torch.equal(a, b)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gsplat_matches_cpu():
    pytest.importorskip("gsplat")
    cam, params = make_scene(0, dtype=torch.float32)
    cpu = render(*params[:5], cam, params[5], backend="cpu")
    gpu_params = leaves([p.cuda() for p in params])
    gpu = render(*gpu_params[:5], cam, gpu_params[5], backend="gsplat")
    assert float((gpu.image.detach().cpu() - cpu.image).abs().mean()) <= 1e-3
    assert float((gpu.alpha.detach().cpu() - cpu.alpha).abs().mean()) <= 1e-3
    assert torch.allclose(gpu.contrib.cpu(), cpu.contrib, rtol=0.05, atol=0.05)
    gpu.image.sum().backward()
    assert gpu.means2d.grad is not None and gpu.means2d.grad.shape == (len(params[0]), 2)


def _bad(**changes):
    cam, params = make_scene(0, n=6, special=False)
    kw = dict(zip(NAMES[:5], params[:5]), camera=cam, background=params[5])
    kw.update(changes)
    return kw


@pytest.mark.parametrize(
    "changes, message",
    [
        (
            lambda kw: {"means": kw["means"].clone().index_fill_(0, torch.tensor([1]), float("nan"))},
            "means contain NaN or inf",
        ),
        (
            lambda kw: {"means": kw["means"].clone().index_fill_(0, torch.tensor([2]), float("inf"))},
            "means contain NaN or inf",
        ),
        (lambda kw: {"scales": kw["scales"].clone().index_fill_(0, torch.tensor([0]), 0.0)}, "scales must be"),
        (lambda kw: {"scales": -kw["scales"]}, "scales must be"),
        (lambda kw: {"opacities": kw["opacities"] + 1.0}, "opacities must be"),
        (lambda kw: {"opacities": -kw["opacities"]}, "opacities must be"),
        (lambda kw: {"quats": torch.zeros_like(kw["quats"])}, "quats must have a non-zero norm"),
        # |q|^2 overflows float64: q / |q| came out 0 and the splat silently unrotated
        (lambda kw: {"quats": kw["quats"] * 1e160}, "quats must have a non-zero norm whose square is finite"),
        (lambda kw: {"quats": kw["quats"][:-1]}, "quats must have shape"),
        (lambda kw: {"colors": kw["colors"][:-1]}, "colors must have shape"),
        (lambda kw: {"means": kw["means"][:, :2]}, "means must have shape"),
        (lambda kw: {"opacities": kw["opacities"][:, None]}, "opacities must have shape"),
        (lambda kw: {"background": torch.zeros(4, dtype=torch.float64)}, "background must have shape"),
        (lambda kw: {"camera": "not a camera"}, "camera must be"),
    ],
)
def test_bad_input_raises_clear_value_error(changes, message):
    kw = _bad()
    kw.update(changes(kw))
    with pytest.raises(ValueError, match=message):
        render(**kw)


def test_zero_size_image_and_bad_options_raise():
    kw = _bad()
    cam = make_camera()
    object.__setattr__(cam, "width", 0)  # Camera refuses this itself; render must too
    kw["camera"] = cam
    with pytest.raises(ValueError, match="image size must be positive"):
        render(**kw)
    with pytest.raises(ValueError, match="image size must be positive"):
        render_numpy(*[kw[k].numpy() for k in NAMES[:5]], cam)
    with pytest.raises(ValueError, match="backend must be"):
        render(**_bad(), backend="vulkan")
    with pytest.raises(ValueError, match="near must be"):
        render(**_bad(), near=0.0)
    with pytest.raises(ValueError, match="eps2d must be"):
        render(**_bad(), eps2d=-0.1)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="needs CUDA"):
            render(**_bad(), backend="gsplat")


@pytest.mark.parametrize(
    "opaque, last_from, upto",
    [
        (False, None, [0, 2, 3]),
        (True, None, [0, 2, 3]),
        (False, 1, [0, 2, 3]),
        (True, 1, [0, 2, 3]),
        (True, 3, [0, 1, 3]),
        (False, 1, [3]),
    ],
)
def test_render_levels_equal_separate_renders_and_reference(opaque, last_from, upto):
    """Nested subsets rendered in one pass: each image is the separate render of its subset
    (to float64 rounding: one pass starts a row's exp recurrence where any image still
    composites), gradients are the sum of the separate renders' gradients and match the
    dense reference, and means2d.grad is the last image's own screen-space gradient. With
    ``last_from`` the last image leaves the levels below it out (the whole avatar without its
    stand-ins), also when some levels then show in no image (last_from 3 after upto 1)."""

    cam, params = make_scene(5, n=300 if opaque else 80)
    rng = np.random.default_rng(5)
    level = rng.integers(0, 4, len(params[0]))
    if opaque:  # pixels stop (T < 1e-4) in the finer images and run on in the coarser ones
        params[3] = torch.where(torch.as_tensor(level) > 0, torch.full_like(params[3], 0.97), params[3])
    weights = [loss_weights(20 + k) for k in range(len(upto))]
    ours = leaves(params)
    outs = render_levels(*ours[:5], cam, ours[5], level=level, upto=upto, last_from=last_from)
    sum((o.image * wi).sum() + (o.alpha * wa).sum() for o, (wi, wa) in zip(outs, weights)).backward()
    assert outs[-1].contrib is not None and (len(upto) == 1 or outs[0].contrib is None)
    if opaque and last_from is None:
        stopped = (outs[-1].alpha.detach() > 0.9995) & (outs[0].alpha.detach() < 0.9)
        assert int(stopped.sum()) > 20

    sep = leaves(params)
    ref = leaves(params)
    total_ref = 0
    for k, u in enumerate(upto):
        low = last_from if last_from is not None and k == len(upto) - 1 else -1
        ids = torch.as_tensor(np.flatnonzero((level <= u) & (level >= low)))
        one = render(*(p[ids] for p in sep[:5]), cam, sep[5])
        assert float((one.image.detach() - outs[k].image.detach()).abs().max()) <= 1e-13
        assert float((one.alpha.detach() - outs[k].alpha.detach()).abs().max()) <= 1e-13
        wi, wa = weights[k]
        ((one.image * wi).sum() + (one.alpha * wa).sum()).backward()
        img, alpha, _ = render_reference(*(p[ids] for p in ref[:5]), cam, ref[5])
        assert float((img.detach() - outs[k].image.detach()).abs().max()) <= 1e-5
        total_ref = total_ref + (img * wi).sum() + (alpha * wa).sum()
    total_ref.backward()
    for name, a, b, c in zip(NAMES, ours, sep, ref):
        assert rel_err(a.grad, b.grad) <= 1e-12, name
        assert rel_err(a.grad, c.grad) <= 1e-3, name
    out = np.ones(len(level), bool)
    out[ids.numpy()] = False  # the Gaussians the last image leaves out: no contrib, no screen gradient
    assert rel_err(outs[-1].contrib[ids], one.contrib) <= 1e-12 and not outs[-1].contrib[out].any()
    assert rel_err(outs[-1].means2d.grad[ids], one.means2d.grad) <= 1e-12
    assert not outs[-1].means2d.grad[out].any()


def test_without_contrib_images_and_gradients_are_unchanged():
    # compute_contrib=False (training, evaluation renders) skips the per-pair alpha*T sums: every
    # other output and every gradient bit for bit the same, contrib None; render_numpy likewise.
    cam, params = make_scene(7, n=200, special=True)
    rng = np.random.default_rng(7)
    level = rng.integers(0, 3, len(params[0]))
    wi, wa = loss_weights(31)
    runs = []
    for want in (True, False):
        ps = leaves(params)
        outs = render_levels(*ps[:5], cam, ps[5], level=level, upto=[0, 2], compute_contrib=want)
        one = render(*leaves(params)[:5], cam, compute_contrib=want)
        sum((o.image * wi).sum() + (o.alpha * wa).sum() for o in outs).backward()
        runs.append((outs, one, [p.grad for p in ps], outs[-1].means2d.grad))
    (outs_c, one_c, grads_c, m2d_c), (outs_n, one_n, grads_n, m2d_n) = runs
    assert outs_c[-1].contrib is not None and one_c.contrib is not None and float(one_c.contrib.sum()) > 0
    assert outs_n[-1].contrib is None and outs_n[0].contrib is None and one_n.contrib is None
    for a, b in zip(outs_c, outs_n):
        assert torch.equal(a.image, b.image) and torch.equal(a.alpha, b.alpha) and torch.equal(a.radii, b.radii)
    assert torch.equal(one_c.image, one_n.image)
    for a, b in zip(grads_c + [m2d_c], grads_n + [m2d_n]):
        assert torch.equal(a, b)
    arrays = [p.detach().numpy() for p in params[:5]]
    img_c, alpha_c, contrib = render_numpy(*arrays, cam)
    img_n, alpha_n, none = render_numpy(*arrays, cam, compute_contrib=False)
    assert none is None and contrib.shape == (len(arrays[0]),)
    assert np.array_equal(img_c, img_n) and np.array_equal(alpha_c, alpha_n)


def test_backward_of_the_last_images_gaussians_alone_equals_the_general_replay():
    """raster_backward replays the Gaussians that only the last image shows on that image's state
    alone when it knows ``upto``; without it every pair takes the general per-image replay. Both
    give the same sums, bit for bit (a forest's finest level takes the first path in training)."""
    from progressive_avatars.core.render import kernels as rk
    from progressive_avatars.core.render import rasterize as rz

    cam, params = make_scene(7, n=300)
    level = np.random.default_rng(7).integers(0, 4, len(params[0]))
    arrays = [p.double().numpy() for p in params]
    upto = np.array([0, 2, 3])
    _, _, _, _, st = rz._cpu_forward(*arrays, cam, 0.01, 0.3, glevel=level, upto=upto, record=True)
    assert (level > upto[-2]).sum() > 30 and (level <= upto[-2]).sum() > 30  # both paths run
    tiles_x, _ = rz._tiles(cam)
    slot_start = rk.backward_slots(st["tile_start"], st["last"])
    rng = np.random.default_rng(8)
    g_img, g_alpha = rng.normal(size=(3, H, W, 3)), rng.normal(size=(3, H, W))
    grads = []
    for kw in ({"upto": upto}, {}):
        scratch = np.empty(rk.scratch_entries(slot_start, 3))
        grads.append(
            rk.raster_backward(
                st["tile_start"],
                st["ids"],
                st["splats"],
                st["gaussian"],
                len(level),
                3,
                st["background"],
                st["t_final"],
                st["last"],
                g_img,
                g_alpha,
                cam.width,
                cam.height,
                tiles_x,
                *st["rec"],
                slot_start,
                scratch,
                **kw,
            )  # fmt: skip
        )
    assert np.abs(grads[0][0]).max() > 0
    assert np.array_equal(grads[0][0], grads[1][0]) and np.array_equal(grads[0][1], grads[1][1])


def test_render_levels_refuses_more_images_than_the_record_holds_and_a_bad_last_from():
    from progressive_avatars.core.render import kernels as rk
    from progressive_avatars.core.render.rasterize import render_levels

    cam, params = make_scene(5, n=20, special=False)
    level = np.arange(20) % (rk.MAX_IMAGES + 1)
    with pytest.raises(ValueError, match="at most 16 images"):
        render_levels(*params[:5], cam, params[5], level=level, upto=list(range(rk.MAX_IMAGES + 1)))
    for bad in (3, 1.5):  # above the last image's level (it would show nothing), not an integer
        with pytest.raises(ValueError, match="last_from must be an integer <= upto"):
            render_levels(*params[:5], cam, params[5], level=level, upto=[0, 2], last_from=bad)


def test_depth_order_is_numpys_stable_argsort():
    # The radix sort of the kernels against numpy's stable argsort: ties (trained avatars have
    # Gaussians at equal depth), a wide range of depths, kept/culled mixes, empty and single.
    from progressive_avatars.core.render import kernels as rk

    rng = np.random.default_rng(5)
    for n in (0, 1, 2, 37, 20_000):
        depth = np.exp(rng.uniform(np.log(0.01), np.log(1e4), n))
        depth[::5] = depth[0] if n else 0.0
        keep = rng.random(n) < 0.8
        expected = np.flatnonzero(keep)[np.argsort(depth[keep], kind="stable")]
        for parts in (1, 2, 3, 8):  # parts sort at once; any split gives the one stable order
            got = rk.depth_order(depth, keep, parts)
            assert got.dtype == np.int64 and np.array_equal(got, expected), (n, parts)


def test_splat_rows_and_tile_lists():
    # The packed rows: a permutation of the visible Gaussians grouped by the tile of their box
    # centre (front to back inside a group), each row holding its Gaussian's values; every tile
    # lists exactly the Gaussians whose box touches it, front to back (ties in depth order).
    from progressive_avatars.core.render import kernels as rk

    rng = np.random.default_rng(8)
    n, tiles_x, tiles_y = 3000, 7, 5
    rect = np.empty((n, 4), np.int32)
    rect[:, 0] = rng.integers(0, tiles_x * rk.TILE, n)
    rect[:, 1] = rng.integers(0, tiles_y * rk.TILE, n)
    rect[:, 2] = np.minimum(rect[:, 0] + rng.integers(0, 40, n), tiles_x * rk.TILE - 1)
    rect[:, 3] = np.minimum(rect[:, 1] + rng.integers(0, 40, n), tiles_y * rk.TILE - 1)
    depth = rng.uniform(1.0, 2.0, n)
    depth[::7] = depth[3]  # ties
    keep = rng.random(n) < 0.9
    order = rk.depth_order(depth, keep)
    m = len(order)
    xy, conic = rng.normal(size=(n, 2)), rng.uniform(0.1, 1.0, size=(n, 3))
    opac, cut, colors = rng.uniform(0.1, 1.0, n), -rng.uniform(0.1, 5.0, n), rng.uniform(size=(n, 3))
    glevel = rng.integers(0, 4, n)

    row_of, gaussian = rk.splat_rows(order, rect, tiles_x, tiles_y)
    assert np.array_equal(np.sort(row_of), np.arange(m)) and np.array_equal(gaussian[row_of], order)
    for parts in (2, 3, 16):  # slices of the depth order grouped at once: the same rows
        rows_p, gaussian_p = rk.splat_rows(order, rect, tiles_x, tiles_y, parts)
        assert np.array_equal(rows_p, row_of) and np.array_equal(gaussian_p, gaussian), parts
    centre = ((rect[:, 1] + rect[:, 3]) // 2 // rk.TILE) * tiles_x + (rect[:, 0] + rect[:, 2]) // 2 // rk.TILE
    key = centre[gaussian]  # the group of each row
    assert np.all(np.diff(key) >= 0)  # rows grouped by centre tile
    rank = np.empty(m, np.int64)
    rank[row_of] = np.arange(m)  # depth rank of each row
    same = np.diff(key) == 0
    assert np.all(np.diff(rank)[same] > 0)  # front to back inside a group

    splats = rk.aligned_splats(m, 3)
    assert splats.ctypes.data % 64 == 0 and splats.shape[1] == rk.splat_width(3) == 16
    rk.pack_splats(gaussian, xy, conic, opac, cut, colors, rect, glevel, splats)
    g = gaussian
    assert np.array_equal(splats[:, rk.S_U], xy[g, 0]) and np.array_equal(splats[:, rk.S_CC], conic[g, 2])
    assert np.array_equal(splats[:, rk.S_ECUT], -2.0 * conic[g, 0] * cut[g])
    assert np.array_equal(splats[:, rk.S_X1], rect[g, 2]) and np.array_equal(splats[:, rk.S_LEVEL], glevel[g])
    assert np.array_equal(splats[:, rk.S_COLOR : rk.S_COLOR + 3], colors[g])

    tile_start, ids = rk.bin_tiles(splats, row_of, tiles_x, tiles_y)
    for t in range(tiles_x * tiles_y):
        tx, ty = t % tiles_x, t // tiles_x
        touch = (
            (rect[:, 0] // rk.TILE <= tx) & (rect[:, 2] // rk.TILE >= tx)
            & (rect[:, 1] // rk.TILE <= ty) & (rect[:, 3] // rk.TILE >= ty)
        )  # fmt: skip
        expected = [q for q in order if touch[q]]  # depth order
        assert list(gaussian[ids[tile_start[t] : tile_start[t + 1]]]) == expected, t


def test_render_bitwise_deterministic_across_runs_and_thread_counts():
    # The per-pair gradient buffers, their parallel gather, the interleaved tile split and the
    # radix depth order must give the same bits whatever the thread count, run after run.
    import numba

    rng = np.random.default_rng(21)
    n = 4000
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    means = d * np.array([0.085, 0.11, 0.095])
    means[::9] = means[1::9][: len(means[::9])]  # equal depths: ties in the depth order
    scales = rng.uniform(2e-3, 8e-3, size=(n, 3))
    params = [
        torch.tensor(x)
        for x in (means, rng.normal(size=(n, 4)), scales, rng.uniform(0.2, 0.98, n), rng.uniform(0, 1, (n, 3)))
    ]
    cam = Camera.look_at([0.05, 0.02, 1.0], [0, 0, 0], [0, 1, 0], 300.0, 300.0, 61.0, 47.0, 120, 96)
    wi = torch.from_numpy(rng.normal(size=(96, 120, 3)))

    def run(threads):
        numba.set_num_threads(threads)
        try:
            ps = leaves(params)
            out = render(*ps, cam)
            ((out.image * wi).sum() + out.alpha.sum()).backward()
            return [out.image.detach(), out.contrib] + [p.grad for p in ps]
        finally:
            numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)

    first = run(1)
    assert float(first[0].abs().sum()) > 0
    for threads in (1, numba.config.NUMBA_NUM_THREADS, numba.config.NUMBA_NUM_THREADS):
        for a, b in zip(first, run(threads)):
            assert torch.equal(a, b)


def test_all_finite_exact_where_the_fast_sum_overflows():
    # The fast path sums; a sum that overflows from huge finite values must not read as NaN/inf.
    from progressive_avatars.core.render.rasterize import all_finite

    huge = torch.full((1000,), 3e38)
    assert math.isinf(float(huge.sum())) and all_finite(huge) and all_finite(huge.numpy())
    for bad in (float("nan"), float("inf"), -float("inf")):
        x = torch.zeros(5000, 3)
        x[4321, 2] = bad
        assert not all_finite(x) and not all_finite(x.numpy()) and not all_finite(x.double())
    pair = torch.tensor([float("inf"), -float("inf")])  # sums to NaN
    assert not all_finite(pair)
    assert all_finite(torch.arange(10)) and all_finite(np.arange(10)) and all_finite(torch.zeros(0))


def test_backward_replays_the_forwards_record_whatever_its_buffers(monkeypatch):
    """The backward replays the pairs the forward recorded. A record that runs out of room is
    made again with more (same gradients, and the next size learnt); forwards that wait for
    their backward together keep their own records; a render under no_grad records nothing; a
    second backward through one render says why it cannot instead of reading a buffer another
    forward may have reused."""
    from progressive_avatars.core.render import rasterize as rz

    cam, params = make_scene(7, n=120)
    wi, wa = loss_weights(7)

    def grads():
        ours = leaves(params)
        out = render(*ours[:5], cam, ours[5])
        ((out.image * wi).sum() + (out.alpha * wa).sum()).backward()
        return [p.grad.clone() for p in ours]

    ref = leaves(params)
    img, alpha, _ = render_reference(*ref[:5], cam, ref[5])
    ((img * wi).sum() + (alpha * wa).sum()).backward()
    roomy = grads()
    small = rz._RecordBuffers(per_pixel=0.001)  # a few entries per thread: the first forward overflows
    monkeypatch.setattr(rz, "_record_buffers", small)
    tight = grads()
    assert small.per_pixel > 0.5
    learnt = small.per_pixel
    with torch.no_grad():  # evaluation: nothing recorded, nothing learnt
        render(*leaves(params)[:5], cam, params[5])
    assert small.per_pixel == learnt
    few = leaves([x[:3] for x in params[:5]])  # a small pass between large ones (a training step's
    render(*few, cam, params[5]).image.sum().backward()  # stand-ins): the size shrinks only slowly
    assert 0.95 * learnt <= small.per_pixel < learnt
    for name, a, b, c in zip(NAMES, tight, roomy, ref):
        assert torch.equal(a, b), name
        assert rel_err(a, c.grad) <= 1e-3, name
    # The backward's per-pair scratch is kept between calls: one too small grows, one left dirty
    # by an earlier backward (here NaN everywhere) is cleared where it is used.
    kept = rz._Scratch()
    kept.array = np.full(5, np.nan)
    monkeypatch.setattr(rz, "_scratch", kept)
    for name, a, b in zip(NAMES, grads(), roomy):
        assert torch.equal(a, b), name
    assert len(kept.array) > 5
    kept.array[:] = np.nan
    for name, a, b in zip(NAMES, grads(), roomy):
        assert torch.equal(a, b), name
    # Two renders alive at once (views per step > 1), the second of other Gaussians.
    a, b = leaves(params), leaves(params)
    with torch.no_grad():
        b[0] += 0.01
    out_a = render(*a[:5], cam, a[5])
    out_b = render(*b[:5], cam, b[5])
    ((out_b.image * wi).sum() + (out_b.alpha * wa).sum()).backward()
    ((out_a.image * wi).sum() + (out_a.alpha * wa).sum()).backward(retain_graph=True)
    for name, g, r in zip(NAMES, a, roomy):
        assert torch.equal(g.grad, r), name
    with pytest.raises(RuntimeError, match="no record"):
        ((out_a.image * wi).sum()).backward()


def test_importance_per_level_is_measured_where_prefixes_show_it(tiny_run, tiny_dataset):
    """Inside a level the stream ranks faces by importance, which matters only for prefixes that
    end in that level: they render the coarser levels and none of the finer ones. Per-level
    importance is each face's alpha*T in exactly that render."""
    from progressive_avatars.core.io import run as runs
    from progressive_avatars.core.io.dataset import Dataset
    from progressive_avatars.core.render.importance import face_importance, view_subset
    from progressive_avatars.core.avatar.avatar import sh_to_rgb, sigmoid

    av = runs.load_run_avatar(tiny_run)
    ds = Dataset(tiny_dataset, "train")
    level = av.forest.level
    assert len(np.unique(level)) >= 4  # coarse levels, template, grown levels
    assert av.forest.backdrop  # trained by default; read here as cumulative levels (every face in every render)
    assert view_subset(10, 3).tolist() == [0, 4, 9] and view_subset(5, None).tolist() == [0, 1, 2, 3, 4]
    # The whole avatar with its backdrop: the finished avatar's render, retired stand-ins behind.
    backdrop = face_importance(av, ds, max_views=3, progress=False, per_level=False)
    faces, behind = av.forest.render_set()
    assert behind is not None and len(behind)
    ev, bg = av.evaluator(), np.asarray(ds.background, np.float32)
    by_hand = np.zeros(av.num_gaussians)
    for i in view_subset(len(ds), 3):
        info = ds.frame_info(int(i))
        m, q, s = ev(ds.vertices_at(info.timestep_index))
        o, c = sigmoid(av.opacity_logit)[faces], sh_to_rgb(av.f_dc)[faces]
        by_hand[faces] += render_numpy(m[faces], q[faces], s[faces], o, c, info.camera, bg, behind=behind)[2]
    np.testing.assert_allclose(backdrop, by_hand, rtol=1e-12)
    av.forest._set_stand_ins(False, None)
    per_level = face_importance(av, ds, max_views=3, progress=False, weighting="alpha")
    # With coarse stand-ins the finished avatar, whose render the whole-avatar importance
    # measures, has none; per level they stay (as in the early prefixes they show in).
    stand_ins = level < av.forest.num_coarse_levels
    assert stand_ins.any()
    av.forest._set_stand_ins(True, None)
    whole = face_importance(av, ds, max_views=3, progress=False, per_level=False)
    assert np.all(whole[stand_ins] == 0) and whole.sum() > 0
    np.testing.assert_array_equal(face_importance(av, ds, max_views=3, progress=False, weighting="alpha"), per_level)
    av.forest._set_stand_ins(False, None)  # cumulative again: every face in every render
    whole = face_importance(av, ds, max_views=3, progress=False, per_level=False)
    finest = level == level.max()
    np.testing.assert_array_equal(per_level[finest], whole[finest])  # its render is the whole avatar
    # Leaving the finer levels out only raises the transmittance in front of a face.
    assert np.all(per_level >= whole - 1e-9 * whole.max())
    assert per_level[~finest].sum() > 1.05 * whole[~finest].sum()
    # One level by hand: the template level's faces in the render of levels <= its own; the
    # default weighs each pixel by the error of the render of the levels below against the image.
    residual = face_importance(av, ds, max_views=3, progress=False)
    tl = av.forest.num_coarse_levels
    by_hand, by_hand_res = np.zeros(av.num_gaussians), np.zeros(av.num_gaussians)
    first_res = np.zeros(av.num_gaussians)  # level 0: weighted by its error against the background
    for i in view_subset(len(ds), 3):
        info = ds.frame_info(int(i))
        m, q, s = ev(ds.vertices_at(info.timestep_index))
        args = lambda sel: (m[sel], q[sel], s[sel], sigmoid(av.opacity_logit)[sel], sh_to_rgb(av.f_dc)[sel])  # noqa: E731
        sel = np.flatnonzero(level <= tl)
        _, _, c = render_numpy(*args(sel), info.camera, bg)
        by_hand[sel] += c
        below, _, _ = render_numpy(*args(np.flatnonzero(level < tl)), info.camera, bg)
        err = np.abs(ds[int(i)].image.astype(np.float64) - below.astype(np.float64)).mean(-1)
        _, _, c = render_numpy(*args(sel), info.camera, bg, pixel_weight=err)
        by_hand_res[sel] += c
        err0 = np.abs(ds[int(i)].image.astype(np.float64) - bg.astype(np.float64)).mean(-1)
        sel0 = np.flatnonzero(level == 0)
        first_res[sel0] += render_numpy(*args(sel0), info.camera, bg, pixel_weight=err0)[2]
    np.testing.assert_allclose(residual[level == 0], first_res[level == 0], rtol=1e-9)
    own = level == tl
    np.testing.assert_allclose(per_level[own], by_hand[own], rtol=1e-12)
    np.testing.assert_allclose(residual[own], by_hand_res[own], rtol=1e-9)
    # Errors are below 1 per pixel, so the weighted sums are smaller, and they rank differently.
    assert np.all(residual <= per_level + 1e-12) and residual[own].sum() > 0
    assert not np.array_equal(np.argsort(residual[own]), np.argsort(per_level[own]))
    with pytest.raises(ValueError, match="weighting"):
        face_importance(av, ds, max_views=1, progress=False, weighting="bogus")


def test_view_subset_takes_the_nearest_view_to_each_even_step():
    """max_views of n views: the views nearest to max_views evenly spaced points from the first
    view to the last (not the ones below them), every view when max_views reaches n."""
    from progressive_avatars.core.render.importance import view_subset

    # 11 views, 4 of them: points 0, 10/3, 20/3, 10 -> nearest views 0, 3, 7, 10 (6 is below 6.67).
    assert view_subset(11, 4).tolist() == [0, 3, 7, 10]
    # 9 views, 4: points 0, 8/3, 16/3, 8 -> 0, 3, 5, 8 (2 and 5 would be the views below).
    assert view_subset(9, 4).tolist() == [0, 3, 5, 8]
    assert view_subset(4, 4).tolist() == view_subset(4, 9).tolist() == view_subset(4, None).tolist() == [0, 1, 2, 3]


def test_pixel_weighted_contribution_is_the_colour_gradient():
    """contrib with pixel weights w is sum_p w_p alpha T per Gaussian: the gradient of
    sum_p w_p image_p with respect to a Gaussian's colour (the backward, an independent path)."""
    rng = np.random.default_rng(3)
    cam = Camera.look_at([0.0, 0.0, 1.0], [0, 0, 0], [0, 1, 0], 90.0, 90.0, 24.0, 20.0, 48, 40)
    n = 60
    means = np.concatenate([rng.uniform(-0.12, 0.12, (n, 2)), rng.uniform(-0.05, 0.05, (n, 1))], 1)
    quats = rng.normal(size=(n, 4))
    scales = rng.uniform(0.01, 0.04, (n, 3))
    opac = rng.uniform(0.2, 0.95, n)
    colors = rng.uniform(0, 1, (n, 3))
    weight = rng.uniform(0, 2, (cam.height, cam.width))
    _, _, plain = render_numpy(means, quats, scales, opac, colors, cam)
    _, _, ones = render_numpy(means, quats, scales, opac, colors, cam, pixel_weight=np.ones_like(weight))
    np.testing.assert_allclose(ones, plain, rtol=1e-12)
    _, _, weighted = render_numpy(means, quats, scales, opac, colors, cam, pixel_weight=weight)
    col = torch.tensor(colors, requires_grad=True)
    t = [torch.tensor(x) for x in (means, quats, scales, opac)]
    out = render(*t, col, cam)
    (out.image[..., 0] * torch.tensor(weight)).sum().backward()
    assert weighted.max() > 0
    np.testing.assert_allclose(weighted, col.grad[:, 0].numpy(), rtol=1e-6, atol=1e-9 * weighted.max())
    with pytest.raises(ValueError, match="pixel_weight"):
        render_numpy(means, quats, scales, opac, colors, cam, pixel_weight=np.ones((3, 3)))
    # With weights or without, one compiled compositing kernel: the omitted weight argument was
    # another signature, and a first run compiled the whole kernel twice.
    from progressive_avatars.core.render import kernels as rk

    assert {str(sig[15]) for sig in rk.raster_forward.signatures} == {"array(float64, 2d, C)"}


def test_float32_inputs_are_read_in_place_and_give_the_float64_gradients_rounded_once():
    """The rasteriser reads float32 parameters without float64 copies and widens every load in its
    kernels: each gradient is the all-float64 render's, rounded once to float32."""
    cam, params = make_scene(6, dtype=torch.float32)
    wi, wa = (w.float().double() for w in loss_weights(6))
    grads = []
    for dtype in (torch.float32, torch.float64):
        ps = [p.detach().to(dtype).clone().requires_grad_(True) for p in params[:5]]
        out = render(*ps, cam, params[5].to(dtype))
        ((out.image.double() * wi).sum() + (out.alpha.double() * wa).sum()).backward()
        grads.append([p.grad for p in ps])
    for g32, g64, name in zip(*grads, NAMES):
        assert g32.dtype == torch.float32 and torch.equal(g32, g64.float()), name
    from progressive_avatars.core.render import rasterize as rz

    shared = rz._kernel_arrays(*params[:5])  # no copies: the kernels get the tensors' own memory
    assert all(np.shares_memory(a, p.numpy()) for a, p in zip(shared, params[:5]))
    mixed = rz._kernel_arrays(*params[:4], params[4].double())  # one kernel per dtype combination at most
    assert all(a.dtype == np.float64 and not np.shares_memory(a, p.numpy()) for a, p in zip(mixed, params[:4]))


def test_an_input_changed_in_place_before_the_backward_is_refused():
    """The backward reads the means, quats and scales from their tensors' memory: torch must refuse
    it after an in-place change rather than differentiate other values than the image shows."""
    cam, params = make_scene(6, dtype=torch.float32)
    ps = [p.clone().requires_grad_(True) for p in params[:5]]
    scales = ps[2] * 1.0  # a non-leaf, as the trainer's activated scales are
    out = render(ps[0], ps[1], scales, *ps[3:5], cam, params[5])
    with torch.no_grad():
        scales.mul_(2.0)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        out.image.sum().backward()


def test_compiled_input_checks_agree_with_the_tensor_checks():
    """render's one-pass check of float32/float64 inputs flags exactly what the torch tests flag
    (the path CUDA tensors and other dtypes take), each bad value alone and all together."""
    from progressive_avatars.core.render import rasterize as rz

    _, params = make_scene(3, n=20, special=False)
    bad = {
        0: [(0, 1, float("nan")), (3, 2, float("-inf"))],
        1: [(2, 0, float("inf"))],
        2: [(1, 1, 0.0), (4, 0, -1e-3), (5, 2, float("nan")), (6, 1, float("inf"))],
        3: [(7, None, 1.5), (8, None, -0.1), (9, None, float("nan"))],
        4: [(10, 2, float("inf"))],
    }
    cases = [(i, [c]) for i, cs in bad.items() for c in cs] + [(None, None)]
    for which, changes in cases:
        ps = [p.clone() for p in params[:5]]
        for i, cs in bad.items() if which is None else [(which, changes)]:
            for row, col, value in cs:
                ps[i][row if col is None else (row, col)] = value
        if which is None:
            ps[1][11] = 0.0  # a zero quaternion beside non-finite ones
        expected = rz._value_flags(*[p.half() for p in ps])  # no compiled path for float16
        assert expected != 0
        for dtype in (torch.float32, torch.float64):
            assert rz._value_flags(*[p.to(dtype) for p in ps]) == expected, (which, changes, dtype)


def test_behind_gaussians_composite_after_all_the_others():
    """``behind`` (retired backdrop stand-ins): the one-pass CPU render, which sorts those
    Gaussians last, equals the two-render composite the gsplat path takes (the others over
    nothing, then the behind ones over the background through what the first left), in image,
    alpha, depth, contrib and every gradient; render_numpy and render_levels agree with it; and
    the result is not the depth-ordered render (the rule changes what is seen)."""
    from progressive_avatars.core.render.rasterize import _render_backdrop

    cam, params = make_scene(3)
    n = params[0].shape[0]
    behind = np.random.default_rng(1).uniform(size=n) < 0.3
    wi, wa = loss_weights(0)
    outs, grads = [], []
    for two in (False, True):
        p = leaves(params)
        if two:
            o = _render_backdrop(
                *p[:5], cam, p[5], behind, near=0.01, eps2d=0.3, return_depth=True, compute_contrib=True, backend="cpu"
            )
        else:
            o = render(*p[:5], cam, p[5], behind=behind, return_depth=True)
        ((o.image * wi).sum() + (o.alpha * wa).sum()).backward()
        outs.append(o), grads.append([x.grad for x in p])
    one, two = outs
    for name in ("image", "alpha", "depth"):
        assert rel_err(getattr(one, name).detach(), getattr(two, name).detach()) < 1e-12, name
    assert rel_err(one.contrib, two.contrib) < 1e-6
    for name, a, b in zip(NAMES, *grads):
        assert rel_err(a, b) < 1e-6, name
    plain = render(*leaves(params)[:5], cam, params[5])
    assert rel_err(plain.image.detach(), one.image.detach()) > 1e-3
    image, alpha, contrib = render_numpy(*(x.numpy() for x in params[:5]), cam, params[5].numpy(), behind=behind)
    assert np.abs(image - one.image.detach().numpy()).max() < 1e-5
    assert rel_err(torch.from_numpy(contrib).double(), one.contrib) < 1e-5
    level = np.random.default_rng(2).integers(0, 3, n)
    outs = render_levels(*leaves(params)[:5], cam, params[5], level=level, upto=[1, 2], behind=behind)
    sub = np.flatnonzero(level <= 1)
    alone = render(*(x[sub] for x in leaves(params)[:5]), cam, params[5], behind=behind[sub])
    assert rel_err(outs[0].image.detach(), alone.image.detach()) < 1e-12
    assert rel_err(outs[1].image.detach(), one.image.detach()) < 1e-12
    with pytest.raises(ValueError, match="behind must be"):
        render(*params[:5], cam, params[5], behind=np.ones(n - 1, bool))


def test_behind_everything_or_nothing_is_the_plain_render():
    """A backdrop of every Gaussian, or of none, composites in plain depth order."""
    cam, params = make_scene(5)
    n = params[0].shape[0]
    plain = render(*params[:5], cam, params[5]).image
    for mask in (np.ones(n, bool), np.zeros(n, bool)):
        assert torch.equal(render(*params[:5], cam, params[5], behind=mask).image, plain)
