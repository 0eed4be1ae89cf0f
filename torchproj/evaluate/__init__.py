"""Evaluation: metrics (PSNR) in model space and, later, on captures."""

from .metrics import model_space_psnr, psnr

__all__ = ["model_space_psnr", "psnr"]
