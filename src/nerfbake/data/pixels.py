"""All training pixels of a split in one uint8 tensor, drawn as random rays or random patches."""
from __future__ import annotations

import numpy as np
import torch

from nerfbake.data.dataset import Dataset
from nerfbake.data.rays import CameraBatch, random_pixels


class PixelStore:
    """Pixels (P, C) uint8 of every image in ``split`` plus the cameras to turn them into rays.

    C is 4 for RGBA datasets (the alpha lets trainers composite on a random background), else 3.
    """

    def __init__(self, ds: Dataset, split: str = "train", progress=None):
        self.indices = ds.split(split)
        self.cameras = CameraBatch([ds.frames[i].camera for i in self.indices])
        keep_alpha = ds.background is not None
        imgs = []
        for k, i in enumerate(self.indices):
            img = ds.image(i, keep_alpha=keep_alpha)
            if keep_alpha and img.shape[-1] == 3:
                img = np.concatenate([img, np.ones_like(img[..., :1])], -1)
            imgs.append(torch.from_numpy(np.round(img * 255).astype(np.uint8)).reshape(-1, img.shape[-1]))
            if progress is not None:
                progress(k + 1, len(self.indices))
        self.channels = imgs[0].shape[-1]
        self.pixels = torch.cat(imgs)
        sizes = torch.tensor([im.shape[0] for im in imgs])
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(sizes, 0)])
        self.background = ds.background

    def __len__(self) -> int:
        return self.pixels.shape[0]

    def sample_rays(self, num_rays: int, generator: torch.Generator, patch: int = 1) -> dict[str, torch.Tensor]:
        """Random rays (or patch x patch squares): origins, directions, cam_idx, target ``rgba``/``rgb`` in [0, 1]."""
        cam, pix = random_pixels(num_rays, self.cameras.sizes, np.arange(len(self.indices)), generator, patch)
        cam, pix = cam.reshape(-1), pix.reshape(-1, 2)
        widths = torch.as_tensor(self.cameras.sizes[:, 0])[cam]
        flat = self.offsets[cam] + pix[:, 1] * widths + pix[:, 0]
        rays = self.cameras.rays(cam, pix)
        rays["target"] = self.pixels[flat].float() / 255.0
        return rays

    def sample_uniform_rays(self, num_rays: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Rays drawn uniformly over all pixels of all images (each pixel equally likely)."""
        flat = torch.randint(0, len(self), (num_rays,), generator=generator)
        cam = torch.searchsorted(self.offsets, flat, right=True) - 1
        local = flat - self.offsets[cam]
        widths = torch.as_tensor(self.cameras.sizes[:, 0])[cam]
        pix = torch.stack([local % widths, local // widths], dim=-1)
        rays = self.cameras.rays(cam, pix)
        rays["target"] = self.pixels[flat].float() / 255.0
        return rays
