"""The `exposure` extension (train/exposure.py): a colour transform per training view, kept to a mean of identity,
applied to training renders only; on a scene whose training photos were taken at different exposures it recovers
the held-out views that training without it loses."""
import shutil

import numpy as np
import pytest
import torch

from train_fixtures import quick_overrides, small_orbit
from warpgs.data.formats.image_io import read_image, write_png
from warpgs.train.exposure import ViewExposures
from warpgs.train.trainer import Trainer

LR = 0.001
BACKGROUND = {"extensions.environment.degree": 2}  # the orbit's sky (as the default run), before the exposure


def test_transforms_start_at_identity_and_keep_a_mean_of_identity():
    ex = ViewExposures(4)
    rgb = torch.rand(5, 6, 3)
    assert torch.equal(ex(rgb, 2), rgb)
    with torch.no_grad():
        ex.deltas.normal_(0.0, 0.3)
    assert torch.allclose(ex.transforms().mean(0), torch.eye(3, 4), atol=1e-6)
    a = ex.transforms()[1]
    assert torch.allclose(ex(rgb, 1), rgb @ a[:, :3].T + a[:, 3])
    with pytest.raises(ValueError, match="at least one training view"):
        ViewExposures(0)


def _exposed_scene(tmp_path, gains: dict):
    """A copy of the small orbit scene whose images were scaled by gains[name] (photos at other exposures)."""
    root = tmp_path / "scene"
    shutil.copytree(small_orbit(), root)
    for name, gain in gains.items():
        path = root / "images" / name
        write_png(path, np.clip(read_image(path)[0] * gain, 0.0, 1.0))
    return root


def test_exposure_recovers_held_out_views_of_differently_exposed_photos(tmp_path):
    probe = Trainer(None, overrides=quick_overrides(tmp_path / "probe"), quiet=True)
    train = [probe.scene.cameras[i].name for i in probe.scene.train]
    rng = np.random.default_rng(0)
    gains = {name: float(g) for name, g in zip(train, rng.uniform(0.55, 1.0, len(train)))}
    # The test photos at the training photos' mean exposure: the appearance the transforms' mean of identity keeps.
    mean_gain = float(np.mean(list(gains.values())))
    gains.update({probe.scene.cameras[i].name: mean_gain for i in probe.scene.test})
    scene = _exposed_scene(tmp_path, gains)

    def held_out_psnr(extra: dict) -> tuple:
        trainer = Trainer(None, overrides=quick_overrides(tmp_path / str(len(extra)), steps=300,
                                                          **{"data.path": str(scene), **BACKGROUND, **extra}),
                          quiet=True)
        result = trainer.fit()
        return result.metrics["psnr"], trainer

    plain, _ = held_out_psnr({})
    compensated, trainer = held_out_psnr({"extensions.exposure.lr": LR})
    print(f"held-out PSNR without / with exposure: {plain:.2f} / {compensated:.2f} dB")
    assert compensated > plain + 1.0
    # The transforms moved; a training view's training render is transformed, its no-gradient render (evaluation,
    # outputs) is not, and a test view's render is the same either way.
    assert trainer.modules["exposure"].deltas.abs().max() > 0.01
    for index, changed in ((trainer.scene.train[0], True), (trainer.scene.test[0], False)):
        view = trainer.views.kept_or_new(index)
        with torch.no_grad():
            raw = trainer.render(view).rgb
        trained = trainer.render(view).rgb.detach()
        assert (not torch.equal(raw, trained)) == changed
