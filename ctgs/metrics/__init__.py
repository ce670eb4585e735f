"""Image quality metrics (SSIM here; PSNR/LPIPS live beside it)."""
