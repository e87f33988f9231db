"""A user's renders and evaluations under torch.inference_mode (common in evaluation code) leave training working:
nothing the library keeps between calls (SSIM's window, the intrinsics memo, the render ops' camera buffers, the
environment map's ray directions) may be an inference tensor that a later differentiated step would save."""
import torch

from warpgs.train.trainer import Trainer


def test_inference_mode_renders_and_evaluations_between_training_steps(tmp_path):
    trainer = Trainer("configs/default.yaml", overrides=["data.width=32", "data.height=24", "train.steps=50",
                                                         "train.device=cpu", "eval.every=0"],
                      quiet=True, out_dir=tmp_path / "run")
    with torch.inference_mode():  # before the first step: every cache is made here first
        trainer.render(trainer.view(0), ("rgb", "depth"))
        before = trainer.evaluate()["psnr"]
    for _ in range(6):
        trainer.train_step()
    with torch.inference_mode():
        after = trainer.evaluate()["psnr"]
    for _ in range(3):
        trainer.train_step()
    assert trainer.step == 9 and torch.isfinite(torch.tensor(trainer.last_loss))
    assert after > before  # it trained
