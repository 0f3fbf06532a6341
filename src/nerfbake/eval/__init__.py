"""Evaluation: image metrics (PSNR, SSIM, LPIPS) and, later, the benchmark harness and reports."""
