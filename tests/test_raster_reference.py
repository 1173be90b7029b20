"""The CPU rasteriser's rules where the random scenes of test_render.py never reach them: alpha
clamped at 0.99 (image and the clamp's zero gradient, on both compositing paths), the 1/255 cut
at faint opacities, a tile's early stop, the near plane's boundary, the field-of-view clamp of
the Jacobian on every side, the radix sort's lowest digit. Expected values come from formulas written out here in
numpy (EWA with eps2d, front-to-back compositing) or from the dense reference with autograd."""

import numpy as np
import torch

from progressive_avatars.core.geometry.camera import Camera
from progressive_avatars.core.render import kernels as rk
from progressive_avatars.core.render.rasterize import render, render_levels
from progressive_avatars.core.render.reference import render_reference

W, H = 32, 24
FX, FY, CX, CY = 40.0, 32.0, 16.0, 12.5
EPS2D = 0.3


def identity_camera(width=W, height=H):
    return Camera(np.eye(3), np.zeros(3), FX, FY, CX, CY, width, height)


def cov2d(mean, s, fx=FX, fy=FY):
    """s^2 J J^T + eps2d I of an isotropic Gaussian of standard deviation s at camera-space
    ``mean`` (inside the clamped field of view), J the Jacobian of (fx x/z + cx, fy y/z + cy)."""
    x, y, z = mean
    J = np.array([[fx / z, 0.0, -fx * x / z**2], [0.0, fy / z, -fy * y / z**2]])
    return s**2 * J @ J.T + EPS2D * np.eye(2)


def by_hand(means, scales, opac, colors, bg, cam=(FX, FY, CX, CY, W, H)):
    """Isotropic Gaussians (quats the identity) under an identity camera (fx, fy, cx, cy, width,
    height), composited front to back at pixel centres: alpha = min(0.99, o exp(-d^T cov2d^-1
    d / 2)), dropped below 1/255, and a pixel stops before the Gaussian that would take its
    transmittance below 1e-4. Returns (image [h, w, 3], alpha of each Gaussian [N, h, w] as
    composited, transmittance in front of each [N, h, w])."""
    fx, fy, cx, cy, w, h = cam
    jj, ii = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    image = np.zeros((h, w, 3))
    T = np.ones((h, w))
    live = np.ones((h, w), bool)
    alphas, fronts = [], []
    for g in np.argsort(means[:, 2], kind="stable"):
        x, y, z = means[g]
        conic = np.linalg.inv(cov2d(means[g], scales[g, 0], fx, fy))
        dx, dy = ii - (fx * x / z + cx), jj - (fy * y / z + cy)
        power = -0.5 * (conic[0, 0] * dx * dx + 2.0 * conic[0, 1] * dx * dy + conic[1, 1] * dy * dy)
        a = np.minimum(opac[g] * np.exp(power), 0.99)
        a = np.where(a >= 1.0 / 255.0, a, 0.0)
        live &= T * (1.0 - a) >= 1e-4
        a = np.where(live, a, 0.0)
        alphas.append(a), fronts.append(T.copy())
        image += (a * T)[..., None] * colors[g]
        T = T * (1.0 - a)
    order = np.argsort(np.argsort(means[:, 2], kind="stable"))
    return image + T[..., None] * bg, np.array(alphas)[order], np.array(fronts)[order]


def tensors(*arrays):
    return [torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in arrays]


def scene():
    """An opaque Gaussian (opacity 1: alpha clamped over its middle) in front of a translucent
    one, and a faint one (opacity 1.5/255: only its middle reaches the 1/255 cut)."""
    means = np.array([[-0.375, -0.375, 2.0], [-0.25, -0.3, 3.0], [0.3, 0.2, 2.5]])  # the first centred on pixel (8, 6)
    scales = np.array([0.6, 0.25, 0.12])[:, None] * np.ones(3)
    opac = np.array([1.0, 0.6, 1.5 / 255.0])
    colors = np.array([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.95]])
    bg = np.array([0.3, 0.1, 0.6])
    return means, np.tile([1.0, 0.0, 0.0, 0.0], (3, 1)), scales, opac, colors, bg


def test_opaque_and_faint_gaussians_composite_as_written_out_by_hand():
    """Image, alpha, contrib and radii of scene() against the formulas written out in by_hand."""
    means, quats, scales, opac, colors, bg = scene()
    image, alphas, fronts = by_hand(means, scales, opac, colors, bg)
    clamped = alphas[0] == 0.99
    faint = alphas[2] > 0
    assert clamped.sum() >= 5 and 0 < faint.sum() < 30 and (fronts[1] < 1).any()  # the rules are exercised
    out = render(*(torch.tensor(a) for a in (means, quats, scales, opac, colors)), identity_camera(), torch.tensor(bg))
    np.testing.assert_allclose(out.image.numpy(), image, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.alpha.numpy(), 1.0 - np.prod(1.0 - alphas, axis=0), rtol=0, atol=1e-12)
    # Under the clamped middle the pixel is 0.99 of the front colour and 1 % of what lies behind.
    j, i = 6, 8
    behind = alphas[1, j, i] * colors[1] + (1.0 - alphas[1, j, i]) * bg
    np.testing.assert_allclose(out.image[j, i].numpy(), 0.99 * colors[0] + 0.01 * behind, rtol=0, atol=1e-12)
    np.testing.assert_allclose(out.contrib.numpy(), (alphas * fronts).sum((1, 2)), rtol=1e-12)
    # The radius: how far alpha >= 1/255 reaches along the wider screen axis, sqrt(2 ln(255 o)) sigma.
    for g in range(3):
        reach = np.sqrt(2.0 * np.log(255.0 * opac[g]) * cov2d(means[g], scales[g, 0]).diagonal().max())
        assert reach <= int(out.radii[g]) < reach + 1.0, g


def test_depth_and_background_gradient_by_hand():
    """With the depth channel: depth is sum z alpha T / alpha, and the background's gradient is
    the incoming image gradient times the final transmittance (the depth channel, an extra
    colour with a zero background inside the kernels, passes nothing to it)."""
    means, quats, scales, opac, colors, bg = scene()
    _, alphas, fronts = by_hand(means, scales, opac, colors, bg)
    t_final = np.prod(1.0 - alphas, axis=0)
    rng = np.random.default_rng(1)
    wi, wd = rng.normal(size=(H, W, 3)), rng.normal(size=(H, W))
    ps = tensors(means, quats, scales, opac, colors, bg)
    out = render(*ps[:5], identity_camera(), ps[5], return_depth=True)
    depth = (means[:, 2, None, None] * alphas * fronts).sum(0) / (1.0 - t_final)
    np.testing.assert_allclose(out.depth.detach().numpy(), depth, rtol=1e-12)
    ((out.image * torch.tensor(wi)).sum() + (out.depth * torch.tensor(wd)).sum()).backward()
    np.testing.assert_allclose(ps[5].grad.numpy(), (wi * t_final[..., None]).sum((0, 1)), rtol=1e-9)


def _clamped_pixel_loss(weights, clamped):
    return lambda image: (image * torch.tensor(weights * clamped[..., None])).sum()


def test_clamped_alpha_passes_no_gradient_to_the_shape_and_opacity():
    """Where alpha is clamped at 0.99 it does not depend on the Gaussian's position, shape or
    opacity: a loss on those pixels alone gives the opaque Gaussian's geometry and opacity zero
    gradients, its colour 0.99 per pixel, and the Gaussian behind it 1 % of its own."""
    means, quats, scales, opac, colors, bg = scene()
    _, alphas, fronts = by_hand(means, scales, opac, colors, bg)
    clamped = alphas[0] == 0.99
    wts = np.random.default_rng(0).normal(size=(H, W, 3))
    loss = _clamped_pixel_loss(wts, clamped)
    # d/do_B of 0.01 (a_B c_B + (1 - a_B) bg), a_B = o_B exp(power): 0.01 (c_B - bg) a_B / o_B.
    g_opac_b = (0.01 * alphas[1] / opac[1] * clamped * ((colors[1] - bg) * wts).sum(-1)).sum()
    g_color = np.stack([(wts * (c * clamped)[..., None]).sum((0, 1)) for c in (0.99, 0.01 * alphas[1])])
    assert abs(g_opac_b) > 1e-3 and (alphas[1][clamped] > 0).all()

    ps = tensors(means, quats, scales, opac, colors)
    loss(render(*ps, identity_camera(), torch.tensor(bg)).image).backward()
    for p in ps[:3]:
        assert float(p.grad[0].abs().max()) == 0.0
    assert float(ps[3].grad[0]) == 0.0
    np.testing.assert_allclose(float(ps[3].grad[1]), g_opac_b, rtol=1e-6)
    np.testing.assert_allclose(ps[4].grad[:2].numpy(), g_color, rtol=1e-5)

    # The same in a pass of nested images: the opaque Gaussian shows in both (level 0), so it takes
    # the per-image compositing and replay; each image's loss adds its share.
    ps = tensors(means, quats, scales, opac, colors)
    outs = render_levels(*ps, identity_camera(), torch.tensor(bg), level=np.array([0, 1, 1]), upto=[0, 1])
    (loss(outs[0].image) + loss(outs[1].image)).backward()
    for p in ps[:3]:
        assert float(p.grad[0].abs().max()) == 0.0
    assert float(ps[3].grad[0]) == 0.0
    np.testing.assert_allclose(float(ps[3].grad[1]), g_opac_b, rtol=1e-6)
    np.testing.assert_allclose(ps[4].grad[0].numpy(), 2.0 * g_color[0], rtol=1e-5)
    np.testing.assert_allclose(ps[4].grad[1].numpy(), g_color[1], rtol=1e-5)


def test_the_near_plane_keeps_a_gaussian_exactly_on_it():
    """Culled means camera z < near: a Gaussian exactly on the near plane renders (here 16 px
    wide), one a float64 step in front of it leaves the background alone."""
    quats, scales, opac = np.array([[1.0, 0.0, 0.0, 0.0]]), np.full((1, 3), 0.004), np.array([0.7])
    colors, bg = np.array([[0.9, 0.4, 0.1]]), np.array([0.2, 0.3, 0.4])
    for z, shown in ((0.01, True), (np.nextafter(0.01, 0.0), False)):
        means = np.array([[0.0, 0.0, z]])
        t = [torch.tensor(a) for a in (means, quats, scales, opac, colors, bg)]
        out = render(*t[:5], identity_camera(), t[5], near=0.01)
        assert (int(out.radii[0]) > 0) == shown
        expected = by_hand(means, scales, opac, colors, bg)[0] if shown else np.broadcast_to(bg, (H, W, 3))
        np.testing.assert_allclose(out.image.numpy(), expected, rtol=0, atol=1e-12)


def test_jacobian_clamp_on_every_side_matches_the_reference_with_gradients():
    """Centres beyond the field of view widened by 30 % (gsplat's clamp of x/z, y/z inside the
    Jacobian), one past each of the four sides with its tail on screen, seen by a camera whose
    principal point is off-centre (so each side has its own limit): image and every gradient
    as the dense reference's with autograd (a clamped x/z or y/z is a constant there)."""
    w, h, fx, fy, cx, cy = 40, 36, 46.0, 39.0, 13.3, 24.6
    cam = Camera(np.eye(3), np.zeros(3), fx, fy, cx, cy, w, h)
    lim = (
        cx / fx + 0.15 * w / fx,
        (w - cx) / fx + 0.15 * w / fx,
        cy / fy + 0.15 * h / fy,
        (h - cy) / fy + 0.15 * h / fy,
    )
    z = np.array([1.5, 1.8, 2.0, 2.2])
    kx = np.array([-(lim[0] + 0.15), lim[1] + 0.1, 0.1, -0.2])
    ky = np.array([0.1, -0.1, -(lim[2] + 0.12), lim[3] + 0.15])
    means = np.stack([kx * z, ky * z, z], 1)
    rng = np.random.default_rng(3)
    params = [
        torch.tensor(a)
        for a in (means, rng.normal(size=(4, 4)), rng.uniform(0.25, 0.4, (4, 3)) * z[:, None], rng.uniform(0.5, 0.9, 4),
                  rng.uniform(0, 1, (4, 3)), np.array([0.2, 0.5, 0.1]))
    ]  # fmt: skip
    wi, wa = torch.from_numpy(rng.normal(size=(h, w, 3))), torch.from_numpy(rng.normal(size=(h, w)))
    ours = [p.clone().requires_grad_(True) for p in params]
    out = render(*ours[:5], cam, ours[5])
    assert (out.radii > 0).all()
    for g in range(4):  # each one shows on screen, so its clamped Jacobian matters
        assert float(out.contrib[g]) > 0.5, g
    ((out.image * wi).sum() + (out.alpha * wa).sum()).backward()
    ref = [p.clone().requires_grad_(True) for p in params]
    img, alpha, _ = render_reference(*ref[:5], cam, ref[5])
    assert float((out.image - img).detach().abs().max()) <= 1e-10
    ((img * wi).sum() + (alpha * wa).sum()).backward()
    for a, b in zip(ours, ref):
        np.testing.assert_allclose(a.grad.numpy(), b.grad.numpy(), rtol=1e-5, atol=1e-7 * float(b.grad.abs().max()))


def test_depth_order_sorts_depths_one_ulp_apart():
    """Depths that differ only in their lowest bits (the radix sort's first 11-bit digit) or only
    in their exponent (its last) still sort."""
    base = np.nextafter(1.0, 2.0)
    ulps = np.array([base + 3 * (base - 1.0), base + 2 * (base - 1.0), base, 1.0, 1.0])
    keep = np.ones(len(ulps), bool)
    assert np.array_equal(rk.depth_order(ulps, keep), [3, 4, 2, 1, 0])
    wide = np.array([1e300, 2.0, 1e-300, 0.5])
    assert np.array_equal(rk.depth_order(wide, np.ones(4, bool)), [2, 3, 1, 0])


def test_a_tile_composites_until_its_last_pixel_stops():
    """One tile (16 x 16 pixels) under two nearly opaque layers (T = 2e-4), then a layer that
    stops every pixel but the corner farthest from its centre, then a faint one that only that
    corner still takes: the tile may end its walk only when every one of its pixels has
    stopped, on the single-image path and on the nested images' path."""
    cam = (32.0, 32.0, 8.0, 8.0, 16, 16)
    corner = 1.2 * 7.5 / 32.0  # the third layer centred on pixel (15.5, 15.5)
    means = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.1], [corner, corner, 1.2], [0.0, 0.0, 1.3]])
    scales = np.array([300.0, 300.0, 0.63, 300.0])[:, None] * np.ones(3)
    opac = np.array([0.98, 1.0, 1.0, 0.015])
    colors = np.array([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.95], [1.0, 1.0, 1.0]])
    bg = np.array([0.3, 0.1, 0.6])
    image, alphas, fronts = by_hand(means, scales, opac, colors, bg, cam)
    assert np.array_equal(np.argwhere(alphas[2] > 0), [[0, 0]]) and np.array_equal(np.argwhere(alphas[3] > 0), [[0, 0]])
    assert 1e-4 < fronts[3][0, 0] * (1.0 - alphas[3][0, 0]) < 1.01e-4
    camera = Camera(np.eye(3), np.zeros(3), *cam)
    t = [torch.tensor(a) for a in (means, np.tile([1.0, 0.0, 0.0, 0.0], (4, 1)), scales, opac, colors, bg)]
    out = render(*t[:5], camera, t[5])
    np.testing.assert_allclose(out.image.numpy(), image, rtol=0, atol=1e-12)
    for level in render_levels(*t[:5], camera, t[5], level=np.zeros(4, np.int64), upto=[0, 1]):
        np.testing.assert_allclose(level.image.numpy(), image, rtol=0, atol=1e-12)
