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
        for index in (0, trainer.train_indices[0]):  # a test view, and a training view the run keeps
            trainer.render(trainer.view(index), ("rgb", "depth"))
        before = trainer.evaluate()["psnr"]  # the evaluation views are chosen (and kept) here
    for _ in range(6):
        trainer.train_step()
    after = trainer.evaluate()["psnr"]  # the same views, now outside inference_mode
    with torch.inference_mode():
        trainer.evaluate()
    for _ in range(len(trainer.train_indices) + 3):  # every training view drawn at least once
        trainer.train_step()
    assert torch.isfinite(torch.tensor(trainer.last_loss))
    assert after > before  # it trained
