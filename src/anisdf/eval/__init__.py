"""Evaluation metrics (PSNR, SSIM, Chamfer distance, normal MAE) and report writing."""
