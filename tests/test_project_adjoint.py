"""The written-out projection adjoint (kernels/project_adjoint.py) against Warp's generated one (what the renderer
launches by default) on the CPU: every input's gradient, for plain colours and SH degrees 0-3, with Gaussians behind
the near plane, far off screen (the field-of-view clamp), with clamped scales, a zero quaternion and some that no
pixel sent a gradient to."""
import numpy as np
import pytest
import warp as wp

from warpgs.kernels import project, project_adjoint

W, H, NEAR, FAR, LOW_PASS = 160, 120, 0.05, 1e10, 0.3


def camera(rng):
    angle = 0.4
    c, s = np.cos(angle), np.sin(angle)
    view = np.eye(4, dtype=np.float32)
    view[:3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float32)
    view[:3, 3] = (0.2, -0.1, 0.5)
    return view, np.array([150.0, 140.0, 82.0, 57.0], np.float32)


def scene(seed, n, num_coeffs):
    rng = np.random.default_rng(seed)
    view, intr = camera(rng)
    R, t = view[:3, :3], view[:3, 3]
    cam = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(0.5, 6.0, n)]
    cam[: n // 10, 2] = rng.uniform(-1.0, NEAR, n // 10)  # behind the near plane: guarded depth
    cam[n // 10: n // 5, 0] = rng.uniform(8.0, 30.0, n // 10) * cam[n // 10: n // 5, 2]  # far off screen: clamped
    means = ((cam - t) @ R).astype(np.float32)  # world points whose camera coordinates are `cam`
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    quats[3] = 0.0  # the guarded zero quaternion
    scales = np.exp(rng.uniform(-3.5, -1.0, (n, 3))).astype(np.float32)
    scales[5, 1] = 2.0e8  # beyond MAX_SCALE: clamped, no gradient
    coeffs = rng.normal(0, 0.4, (n, num_coeffs, 3)).astype(np.float32)
    g = [rng.normal(size=(n, k)).astype(np.float32) for k in (2, 3, 3, 1)]
    cold = rng.random(n) < 0.25  # no upstream gradient at all
    for a in g:
        a[cold] = 0.0
    return dict(means=means, quats=quats, scales=scales, coeffs=coeffs, view=view, intr=intr, g=g)


def cpu(a, dtype):
    return wp.array(a, dtype=dtype, device="cpu")


def gradients(sc, color_mode, degree, written_out):
    n = sc["means"].shape[0]
    inputs = [cpu(sc["means"], wp.vec3), cpu(sc["quats"], wp.vec4), cpu(sc["scales"], wp.vec3),
              wp.array(sc["coeffs"], dtype=wp.vec3, device="cpu"), cpu(sc["view"][None], wp.mat44),
              cpu(sc["intr"][None], wp.vec4)]
    grads = [wp.zeros(n, dtype=wp.vec3, device="cpu"), wp.zeros(n, dtype=wp.vec4, device="cpu"),
             wp.zeros(n, dtype=wp.vec3, device="cpu"),
             wp.zeros(sc["coeffs"].shape[:2], dtype=wp.vec3, device="cpu")]
    g = [cpu(sc["g"][0], wp.vec2), cpu(sc["g"][1], wp.vec3), cpu(sc["g"][2], wp.vec3), cpu(sc["g"][3][:, 0], float)]
    if written_out:
        want = (project_adjoint.WANT_MEANS | project_adjoint.WANT_QUATS | project_adjoint.WANT_SCALES
                | project_adjoint.WANT_COEFFS)
        wp.launch(project_adjoint.project_gaussians_adjoint, dim=n,
                  inputs=inputs + [W, H, NEAR, color_mode, degree, LOW_PASS] + g + [want] + grads, device="cpu")
    else:
        outs = [wp.zeros(n, dtype=dt, device="cpu") for dt in (wp.vec2, wp.vec3, wp.vec3, float, wp.vec3, wp.int32)]
        args = inputs + [W, H, NEAR, FAR, color_mode, degree, LOW_PASS] + outs + g
        adj = grads + [None, None, 0, 0, 0.0, 0.0, 0, 0, 0.0, g[0], g[1], None, g[3], g[2], None] + [None] * 4
        wp.launch(project.project_gaussians_reached, dim=n, inputs=args, adj_inputs=adj, adjoint=True, device="cpu")
    return [a.numpy() for a in grads]


@pytest.mark.parametrize("color_mode, degree, num_coeffs", [(project.COLOR_DIRECT, 0, 1), (project.COLOR_SH, 0, 1),
                                                           (project.COLOR_SH, 1, 4), (project.COLOR_SH, 2, 9),
                                                           (project.COLOR_SH, 3, 16)])
@pytest.mark.parametrize("upstream", ["all", "colour only"])  # colour only: the view direction's share of the
def test_written_out_adjoint_matches_the_generated_one(color_mode, degree, num_coeffs, upstream):  # means' gradient
    sc = scene(degree + 10 * color_mode, 400, num_coeffs)
    if upstream == "colour only":
        for k in (0, 1, 3):
            sc["g"][k][:] = 0.0
    want = gradients(sc, color_mode, degree, written_out=False)
    got = gradients(sc, color_mode, degree, written_out=True)
    rows = np.arange(len(sc["means"])) != 5  # the clamped one spans ~1e8: its other gradients are float32 noise
    for name, a, b in zip(("means", "quats", "scales", "coeffs"), got, want):
        assert np.isfinite(a).all(), name
        scale = np.abs(b[rows]).max()
        if scale == 0:  # colour only: no geometry gradient (plain colours: none for the means either)
            assert upstream == "colour only" and name != "coeffs" and not a.any(), name
            continue
        np.testing.assert_allclose(a[rows], b[rows], rtol=2e-4, atol=2e-5 * scale, err_msg=name)
    # The clamped scale and the Gaussians without upstream gradients got none from either.
    assert got[2][5, 1] == 0.0 == want[2][5, 1]
    cold = ~np.any([np.any(a != 0, axis=1) if a.ndim > 1 else a != 0 for a in sc["g"]], axis=0)
    assert cold.sum() > 50 and not got[0][cold].any()


@pytest.mark.parametrize("sh_degree", [None, 1, 3])
def test_the_op_with_the_written_adjoint_matches_the_float64_reference(sh_degree, monkeypatch):
    """The render op under raster_options(project_adjoint="written"), camera not differentiated (the case it
    covers), against autograd on the float64 reference; it must really have run."""
    import torch

    from random_scenes import random_scene
    from raster_helpers import render_ours, render_ref
    from warpgs.render import fast_pipeline
    from warpgs.render.defaults import raster_options

    launched = []
    real = fast_pipeline.launch_written_projection_adjoint
    monkeypatch.setattr(fast_pipeline, "launch_written_projection_adjoint",
                        lambda *a, **k: launched.append(1) or real(*a, **k))
    scene = random_scene(n=40, seed=7, sh_degree=sh_degree)
    scene["viewmat"][:3, 3] += torch.tensor([0.05, -0.03, 0.1], dtype=torch.float64)
    g = torch.Generator().manual_seed(11)
    H, W = scene["height"], scene["width"]
    weights = {"rgb": torch.randn(H, W, 3, generator=g, dtype=torch.float64),
               "depth": torch.randn(H, W, 1, generator=g, dtype=torch.float64)}
    names = ("means", "quats", "scales", "opacities", "colors")

    def grads(render, dtype):
        leaves = {k: scene[k].detach().to(dtype).requires_grad_(True) for k in names}
        out = render(dict(scene, **leaves))
        get = (lambda n: out[n]) if isinstance(out, dict) else (lambda n: getattr(out, n))
        sum((get(n).double() * w).sum() for n, w in weights.items()).backward()
        return {k: v.grad.double() for k, v in leaves.items()}

    with raster_options(project_adjoint="written"):
        ours = grads(lambda s: render_ours(s, ("rgb", "depth")), torch.float32)
    ref = grads(lambda s: render_ref(s), torch.float64)
    assert launched
    for name in names:
        a, b = ours[name].flatten(), ref[name].flatten()
        cosine = torch.nn.functional.cosine_similarity(a, b, dim=0).item()
        rel = ((a - b).norm() / b.norm()).item()
        assert cosine >= 0.999 and rel <= 1e-3, f"{name}: cosine {cosine:.6f}, relative L2 {rel:.2e}"


def test_a_flat_gaussian_1e7_long_at_the_near_plane_gets_finite_gradients():
    """A case the stress test drew: with its conic computed through a c - b^2 (float32 noise here) the written
    adjoint's chain overflowed and inf * 0 made NaN. The conic is exact now (next test), and a gradient that still
    overflowed float32 with a finite upstream would be dropped (0), never NaN."""
    import torch

    from warpgs import rasterize

    view = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.9787233414018174, 0.20518435855411005, 0.0],
                         [0.0, -0.20518435855411005, 0.9787233414018174, 0.0], [0.0, 0.0, 0.0, 1.0]])
    leaves = dict(means=torch.tensor([[0.3906983949401768, -0.0387488684181143, 0.01]]), quats=torch.zeros(1, 4),
                  scales=torch.tensor([[0.0, 0.0, 11674787.0]]), opacities=torch.tensor([0.33050397752616]),
                  colors=torch.tensor([[0.006398980984146485, 0.21518027277130025, 0.471673078714696]]))
    leaves = {k: v.requires_grad_(True) for k, v in leaves.items()}
    outputs = ("rgb", "alpha", "depth", "inv_depth")
    out = rasterize(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"], view,
                    torch.tensor([[22.0, 0.0, 1.0], [0.0, 22.0, 11.0], [0.0, 0.0, 1.0]]), 2, 22, outputs=outputs,
                    background=torch.tensor([0.2, 0.4, 0.6]))
    sum((getattr(out, o) * (i + 1)).sum() for i, o in enumerate(outputs)).backward()
    assert out.num_intersections > 0  # it reaches the image's tiles
    for name, leaf in leaves.items():
        assert torch.isfinite(leaf.grad).all(), name


@pytest.mark.parametrize("rows", [((0.0, 0.0, 2.6e10), (0.0, 0.0, 1.3e10)),  # a needle seen side on (rank 1)
                                  ((3.0e3, 1.0, -2.0e3), (6.0e3, 2.5, -4.0e3)),  # nearly parallel rows
                                  ((1.5, -0.2, 0.7), (0.3, 2.0, -0.1))])  # an ordinary footprint
def test_the_conic_is_the_exact_inverse_of_a_thin_footprint(rows):
    """covariance_inverse against the inverse in float64 with its determinant written without cancellation
    (|t0 x t1|^2 + lp (|t0|^2 + |t1|^2) + lp^2): a c - b^2 of a needle seen side on is float32 (even float64)
    noise, and the conic came out wrong by orders of magnitude."""
    from warpgs.kernels import gaussian_math

    @wp.kernel
    def conic(t0: wp.array(dtype=wp.vec3), t1: wp.array(dtype=wp.vec3), lp: float, out: wp.array(dtype=wp.vec3)):
        a = wp.dot(t0[0], t0[0]) + lp
        b = wp.dot(t0[0], t1[0])
        c = wp.dot(t1[0], t1[0]) + lp
        out[0] = gaussian_math.covariance_inverse(t0[0], t1[0], lp, a, b, c)

    t0, t1 = (np.array(r, np.float32) for r in rows)
    out = wp.zeros(1, dtype=wp.vec3, device="cpu")
    wp.launch(conic, 1, inputs=[cpu(t0[None], wp.vec3), cpu(t1[None], wp.vec3), LOW_PASS, out], device="cpu")
    u0, u1 = t0.astype(np.float64), t1.astype(np.float64)
    det = np.dot(np.cross(u0, u1), np.cross(u0, u1)) + LOW_PASS * (u0 @ u0 + u1 @ u1) + LOW_PASS**2
    want = np.array([u1 @ u1 + LOW_PASS, -(u0 @ u1), u0 @ u0 + LOW_PASS]) / det
    np.testing.assert_allclose(out.numpy()[0], want, rtol=1e-5, atol=1e-6 * np.abs(want).max())


def test_the_written_adjoint_writes_rather_than_adds():
    """Its callers hand it zero-filled gradients, so it writes each Gaussian's gradients (no read back): a second
    launch into the same arrays leaves them as the first left them."""
    sc = scene(3, 200, 16)
    once = gradients(sc, project.COLOR_SH, 3, written_out=True)
    n = sc["means"].shape[0]
    inputs = [cpu(sc["means"], wp.vec3), cpu(sc["quats"], wp.vec4), cpu(sc["scales"], wp.vec3),
              wp.array(sc["coeffs"], dtype=wp.vec3, device="cpu"), cpu(sc["view"][None], wp.mat44),
              cpu(sc["intr"][None], wp.vec4)]
    grads = [cpu(once[0], wp.vec3), cpu(once[1], wp.vec4), cpu(once[2], wp.vec3),
             wp.array(once[3], dtype=wp.vec3, device="cpu")]  # the first launch's gradients, launched into again
    g = [cpu(sc["g"][0], wp.vec2), cpu(sc["g"][1], wp.vec3), cpu(sc["g"][2], wp.vec3), cpu(sc["g"][3][:, 0], float)]
    want = (project_adjoint.WANT_MEANS | project_adjoint.WANT_QUATS | project_adjoint.WANT_SCALES
            | project_adjoint.WANT_COEFFS)
    wp.launch(project_adjoint.project_gaussians_adjoint, dim=n,
              inputs=inputs + [W, H, NEAR, project.COLOR_SH, 3, LOW_PASS] + g + [want] + grads, device="cpu")
    for name, first, second in zip(("means", "quats", "scales", "coeffs"), once, grads):
        np.testing.assert_array_equal(second.numpy(), first, err_msg=name)
