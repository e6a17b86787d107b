"""Metrics: images (PSNR, SSIM, LPIPS), physics predictions, and trajectories against reference videos."""
