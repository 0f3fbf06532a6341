"""Per-image appearance: real photos differ in exposure and white balance (a phone's auto exposure above all),
and a field that must reproduce each photo's colours exactly explains the differences with view-dependent
colour and floaters. Each training image gets an affine colour correction ``rgb' = (I + A_i) rgb + b_i``
(a 3x3 matrix and an offset, Urban Radiance Fields' and Zip-NeRF's per-image affine model, 12 numbers) applied
to the teacher's rendered colour before the loss.

The corrections are centred: the mean over images is subtracted, so the teacher's own colour is the mean
appearance of the training photos. That is what every later stage (octree, SMERF, held-out evaluation) sees;
held-out photos are scored against the mean appearance, with no per-image fitting (the stricter choice: NeRF-W
and nerfstudio fit a code on half of each test image).
"""
from __future__ import annotations

import torch
from torch import nn

APPEARANCE_MODES = ("auto", "affine", "none")
# The corrections' learning rate relative to the field's: twelve numbers per image, each fitted from every ray of
# its image in a batch, settle fast; at the field's rate they would chase its early blur.
APPEARANCE_LR_SCALE = 0.1


def resolve_appearance(mode: str, has_alpha: bool) -> str:
    """``auto``: affine for photographs, none for RGBA renders (synthetic scenes have one exposure)."""
    if mode not in APPEARANCE_MODES:
        raise ValueError(f"unknown appearance mode {mode!r}; choose one of {', '.join(APPEARANCE_MODES)}")
    if mode == "auto":
        return "none" if has_alpha else "affine"
    return mode


class ImageAppearance(nn.Module):
    """Centred per-image affine colour corrections for ``num_images`` training images."""

    def __init__(self, num_images: int):
        super().__init__()
        self.params = nn.Parameter(torch.zeros(num_images, 12))

    def centred(self) -> torch.Tensor:
        return self.params - self.params.mean(dim=0, keepdim=True)

    def forward(self, rgb: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """``rgb`` (R, 3) as the teacher renders it, ``image`` (R,) training-image indices -> (R, 3)."""
        p = self.centred()[image]
        matrix, offset = p[:, :9].view(-1, 3, 3), p[:, 9:]
        return rgb + torch.einsum("rij,rj->ri", matrix, rgb) + offset

    def summary(self) -> dict:
        """How far the images' corrections spread: largest offset and matrix entry (0 for identical photos)."""
        p = self.centred().detach()
        return {"max_offset": float(p[:, 9:].abs().max()), "max_matrix": float(p[:, :9].abs().max())}
