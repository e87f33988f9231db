"""Issue 12: training on a real phone capture (1080x1920 at 1/2, random init) fell from 13.7 to 5.5 dB held-out
PSNR at the first size-pruning refine after the opacity reset, the primitives from 366k to a few thousand.
Causes: a screen-size rule in absolute pixels (20 px is 2% of a 960 px image) and a world-size rule measured
against the cameras' radius, which is tiny when the cameras barely move. These tests pin the scale-aware rules,
the robust extent and the warning a collapsing refine gives."""
import math
import warnings

import numpy as np
import pytest
import torch

from warpgs.cli.commands import resolve_config_source
from warpgs.config.loader import load_config
from warpgs.data.camera import Camera, intrinsics_matrix, look_at
from warpgs.model.gaussians import GaussianModel
from warpgs.train.optim import build_optimizer
from warpgs.train.screen_geometry import screen_radii
from warpgs.train.strategy import DensifyStrategy, PruningWarning, StrategyConfig

PHONE = (540, 960, 760.0)  # the report's 1080x1920 portrait capture at data.downscale=2: width, height, focal px


def preset_strategy(**changes) -> StrategyConfig:
    cfg = load_config(resolve_config_source("gaussians")).strategy
    for k, v in changes.items():
        setattr(cfg, k, v)
    return cfg


def walk_around_rig(width, height, f, n=12, radius=3.0):
    """Phone cameras on a circle around the origin, looking at it (the usual object capture)."""
    K = intrinsics_matrix(f, f, width / 2, height / 2)
    eyes = [(radius * math.cos(a), radius * math.sin(a), 0.3) for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]
    return [Camera(K, look_at(e, (0.0, 0.0, 0.0)), width, height, name=f"{i}") for i, e in enumerate(eyes)]


def camera_extent(cams):
    c = np.stack([cam.center for cam in cams])
    return 1.1 * float(np.linalg.norm(c - c.mean(0), axis=1).max())  # 3DGS's (Scene.camera_extent)


def subject(extra_means=(), extra_scales=(), n=400, seed=0):
    """A well-fitted subject: n primitives on a 0.8-radius sphere, 0.02-0.06 in scale (3-sigma radii of 2-7% of a
    960 px image from 3 m), opacity 0.6; then the extra primitives (rows n, n+1, ...)."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    means = 0.8 * d / d.norm(dim=1, keepdim=True)
    scales = torch.exp(torch.empty(n).uniform_(math.log(0.02), math.log(0.06), generator=g))
    means = torch.cat([means, torch.tensor(np.array(extra_means, dtype=np.float32)).reshape(-1, 3)])
    scales = torch.cat([scales, torch.tensor(list(extra_scales), dtype=torch.float32)])
    m = len(means)
    op = torch.full((m,), 0.6)
    return GaussianModel(means, scales.log()[:, None].repeat(1, 3), torch.randn(m, 4, generator=g),
                         torch.log(op / (1 - op)), torch.rand(m, 1, 3, generator=g), torch.zeros(m, 3, 3))


def first_size_prune(model, cams, cfg, extent):
    """Cold gradients (nothing densifies) from every camera up to the first refine after size_prune_start;
    returns the indices of the primitives that survive it."""
    model.add_extra("row", torch.arange(model.num_primitives, dtype=torch.float32)[:, None])
    opt = build_optimizer(model)
    s = DensifyStrategy(cfg, scene_extent=extent)
    s.initialize(model)
    step = cfg.size_prune_start + cfg.refine_every - cfg.size_prune_start % cfg.refine_every
    for i, st in enumerate(range(step - len(cams) + 1, step + 1)):
        cam = cams[i % len(cams)]
        V, K = torch.tensor(cam.viewmat, dtype=torch.float32), torch.tensor(cam.K, dtype=torch.float32)
        n = model.num_primitives
        visible = screen_radii(model, V, K, cam.width, cam.height) > 0
        s.step_post_backward(model, opt, st, visible=visible, viewmat=V, K=K, width=cam.width, height=cam.height,
                             grad2d=torch.zeros(n, 2))
    return set(model.params["row"][:, 0].long().tolist())


def test_preset_keeps_a_phone_capture_at_full_resolution():
    cams = walk_around_rig(*PHONE)
    giant = 400  # scale 1.0 > 0.1 x extent 3.3: the world-size rule's job
    model = subject(extra_means=[(0.0, 0.0, 0.0)], extra_scales=[1.0])
    radii = screen_radii(model, torch.tensor(cams[0].viewmat, dtype=torch.float32),
                         torch.tensor(cams[0].K, dtype=torch.float32), PHONE[0], PHONE[1])[:giant]
    assert (radii > 20).float().mean() > 0.3  # many legitimately exceed the old 20 px rule...
    assert radii.max() < 0.1 * PHONE[1]  # ...though none covers a tenth of the image
    kept = first_size_prune(model, cams, preset_strategy(), camera_extent(cams))
    assert giant not in kept
    assert len(kept & set(range(giant))) == giant  # the subject survives whole (it lost ~half to the 20 px rule)


@pytest.mark.parametrize("screen_size", [None, 0.15])
def test_size_pruning_does_not_depend_on_the_resolution(screen_size):
    # A near floater 0.3 in front of camera 0 covers ~a quarter of its image: pruned when the screen rule is on.
    cam0 = walk_around_rig(*PHONE)[0]
    floater = cam0.center + 0.3 * cam0.forward
    changes = {} if screen_size is None else {"prune_screen_size": screen_size}
    survivors = []
    for factor in (1, 8):
        w, h, f = PHONE
        cams = walk_around_rig(w // factor, h // factor, f / factor)
        model = subject(extra_means=[floater], extra_scales=[0.03])
        survivors.append(first_size_prune(model, cams, preset_strategy(**changes), camera_extent(cams)))
    assert survivors[0] == survivors[1]
    assert (400 in survivors[0]) == (screen_size is None) and set(range(400)) <= survivors[0]


def test_a_refine_that_removes_most_primitives_warns_by_rule():
    model = subject(n=4)
    with torch.no_grad():
        model.params["logit_opacities"][:3] = -8.0  # opacity 3e-4 < prune_opacity
        model.params["log_scales"][0] = math.log(5.0)  # also too large: counted under both rules
    opt = build_optimizer(model)
    s = DensifyStrategy(StrategyConfig(), scene_extent=3.0, invisible_below=1 / 255)
    s.initialize(model)
    with pytest.warns(PruningWarning, match=r"pruned 3 of 4 primitives .*opacity < 0.005: 3, .*invisible.*: 0, "
                                         r"world size > 0.1 x extent 3: 1, screen size \(off\): 0"):
        report = s.refine(model, opt, step=3100)
    assert report["pruned_by"] == {"opacity": 3, "invisible": 0, "world_size": 1, "screen_size": 0}
    assert s.last_refine is report and model.num_primitives == 1
    # Removing half or less is routine: no warning.
    model = subject(n=4)
    with torch.no_grad():
        model.params["logit_opacities"][:2] = -8.0
    s.initialize(model)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert s.refine(model, build_optimizer(model), step=3200)["pruned"] == 2


def test_invisible_primitives_are_counted_apart_from_faint_ones():
    model = subject(n=3)
    with torch.no_grad():
        model.params["logit_opacities"][:] = torch.tensor([-8.0, math.log(0.01 / 0.99), 0.0])  # 3e-4, 0.01, 0.5
    s = DensifyStrategy(StrategyConfig(), invisible_below=0.02)
    s.initialize(model)
    rules = s.prune_rules(model, step=600)
    assert rules["opacity"].tolist() == [True, False, False] and rules["invisible"].tolist() == [False, True, False]


def test_legacy_pixel_threshold_warns_and_still_works():
    with pytest.warns(PruningWarning, match="prune_screen_radius=20 px is not scale-aware"):
        s = DensifyStrategy(StrategyConfig(prune_screen_radius=20.0))
    assert s.config.prune_screen_radius == 20.0
    with pytest.raises(ValueError, match="prune_screen_size.*fraction.*prune_screen_radius"):
        StrategyConfig(prune_screen_size=20.0)  # pixels given to the fraction


def test_forward_facing_capture_survives_the_first_size_prune(tmp_path):
    """End to end on the synthetic 3x3 light field (cameras 0.3 apart, the scene ~4 away: 3DGS's extent is 0.47),
    the preset's rules on a compressed schedule: reset at 100, size pruning from then on. Before the fix the
    world-size rule (0.1 x 0.47) deleted 40% of the model at step 125, the ground and sky with it, and held-out
    PSNR fell from 11.2 dB to 6.4 dB; now the extent is what the cameras see (2.4)."""
    from warpgs.data.formats.synthetic import RigSettings, write_synthetic_scene
    from warpgs.train.trainer import Trainer

    scene = write_synthetic_scene(tmp_path / "lf", "lightfield", RigSettings(width=64, height=48), n_points=1500)
    overrides = [f"data.path={scene}", f"output.dir={tmp_path / 'out'}", "train.device=cpu", "train.steps=200",
                 "train.progress=false", "train.checkpoint_every=0", "eval.every=100", "eval.lpips=false",
                 "eval.save_images=false", "model.sh_interval=50", "strategy.refine_start=25",
                 "strategy.refine_every=25", "strategy.reset_every=100", "strategy.size_prune_start=100",
                 "strategy.refine_stop_fraction=1"]  # densify to the end: the test is about the pruning after the reset
    reports = []
    trainer = Trainer(resolve_config_source("gaussians"), overrides=overrides, quiet=True,
                      callbacks=[lambda t, step, info: info["densify"] and reports.append(info["densify"])])
    result = trainer.fit()
    first = next(r for r in reports if r["step"] > 100 and "pruned" in r)
    assert first["pruned"] < 0.1 * first["num_primitives"]
    psnr_before_reset = result.history[0]["psnr"]  # step 100
    assert result.history[0]["step"] == 100
    assert result.metrics["psnr"] > psnr_before_reset + 1.0
    assert trainer.extent < 0.5 and trainer.strategy.world_extent > 2.0  # lr keeps 3DGS's; pruning, what is seen


def sweep_rig(n=10, spread=0.1, toe_in_at=None):
    """A forward-facing phone sweep: cameras along x within `spread`, looking along +y (or all at the point
    toe_in_at metres ahead)."""
    w, h, f = PHONE
    K = intrinsics_matrix(f, f, w / 2, h / 2)
    cams = []
    for i, x in enumerate(np.linspace(-spread / 2, spread / 2, n)):
        target = (0.0, toe_in_at, 0.0) if toe_in_at else (x, 1.0, 0.0)
        cams.append(Camera(K, look_at((x, 0.0, 0.0), target), w, h, name=f"{i}"))
    return cams


HALF_FOV = 0.5 * 960 / 760  # the larger half-side over the focal length


def test_content_extent_of_an_object_capture_is_3dgs_extent():
    from warpgs.data.extent import content_extent

    cams = walk_around_rig(*PHONE)
    assert content_extent(cams) == pytest.approx(camera_extent(cams))
    points = np.random.default_rng(0).normal(size=(500, 3)) * 0.5
    assert content_extent(cams, points) == pytest.approx(camera_extent(cams))


def test_content_extent_when_the_cameras_barely_move():
    from warpgs.data.extent import content_extent

    cams = sweep_rig()
    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(-3, 3, 2000), rng.uniform(4, 6, 2000), rng.uniform(-4, 4, 2000)]
    behind = wall * np.array([1.0, -1.0, 1.0]) * 10  # behind every camera: ignored
    assert camera_extent(cams) == pytest.approx(0.055)
    got = content_extent(cams, np.r_[wall, behind[:100]])
    assert got == pytest.approx(1.1 * np.median(wall[:, 1]) * HALF_FOV, rel=0.02)
    # No points: where the optical axes meet, else (parallel axes) only the cameras' spread is known.
    assert content_extent(sweep_rig(toe_in_at=5.0)) == pytest.approx(1.1 * 5.0 * HALF_FOV, rel=1e-3)
    assert content_extent(cams) == pytest.approx(camera_extent(cams))
    assert content_extent(cams[:1]) == 1.0  # one camera, nothing seen: the 3DGS fallback
