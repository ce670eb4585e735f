"""Image quality metrics: PSNR (psnr), SSIM (ssim), LPIPS (lpips, its VGG16 weights: vgg_weights). A leaf:
evaluating a run with them is ctgs.evaluation."""
