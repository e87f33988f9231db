"""The package layout: the public API, the subpackages' exports, console entry points, and that light subpackages
do not load Warp."""
import subprocess
import sys


def test_public_api_names():
    import warpgs
    from warpgs import RenderOutput, Trainer, load_config, rasterize, rasterize_surfels, register_loss  # noqa: F401
    assert callable(rasterize) and callable(rasterize_surfels) and callable(load_config)
    assert warpgs.Trainer.__module__ == "warpgs.train.trainer"


def test_old_package_paths_still_export_what_users_import():
    from warpgs.render import RenderOutput, rasterize  # noqa: F401  (warpgs.render was a module)
    from warpgs.train import NonFiniteError, Trainer  # noqa: F401  (warpgs.train was a module)
    from warpgs.config import Config, ConfigError, TrainConfig, load_config  # noqa: F401
    from warpgs.metrics import LPIPSMetric, psnr, ssim  # noqa: F401
    from warpgs.cli import eval_main, render_main, train_main  # noqa: F401


def test_config_losses_and_data_import_without_warp():
    code = ("import sys, warpgs.config, warpgs.losses, warpgs.data, warpgs.metrics; "
            "assert 'warp' not in sys.modules, sorted(m for m in sys.modules if m.startswith('warp'))")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_python_dash_m_cli_names_its_commands():
    out = subprocess.run([sys.executable, "-m", "warpgs.cli"], capture_output=True, text=True)
    assert out.returncode != 0 and "train" in out.stderr and "render" in out.stderr
