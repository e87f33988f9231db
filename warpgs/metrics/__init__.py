"""Metrics: image quality (PSNR, SSIM, LPIPS when its weights are local), held-out evaluation of rendered views,
and the depth metrics of the sparse-view study."""
from warpgs.metrics.image import LPIPSMetric, image_metrics, lpips_unavailable_reason, psnr, ssim, to_bchw  # noqa: F401

__all__ = ["psnr", "ssim", "LPIPSMetric", "image_metrics", "lpips_unavailable_reason", "to_bchw"]
