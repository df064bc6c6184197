"""Random shifts of preprocessed frames, for PPO's ``--augment`` (DrAC, Raileanu et al. 2021;
the shift is DrQ's and RAD's augmentation, Kostrikov et al. 2020, Laskin et al. 2020)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

AUGMENT_SHIFT = 4
"""Pixels either way of the network's input (56x56 by default: DrQ's 4 at 84 px, a little
more of the frame)."""


def random_shift(frames: torch.Tensor, rng: np.random.Generator,
                 shift: int = AUGMENT_SHIFT) -> torch.Tensor:
    """``frames`` (NCHW) each moved by its own whole-pixel offset in ``-shift .. shift`` down
    and across, drawn from ``rng``; what comes in at an edge repeats the edge's pixels."""
    n, _, height, width = frames.shape
    offsets = torch.from_numpy(rng.integers(0, 2 * shift + 1, size=(n, 2))).to(frames.device)
    padded = F.pad(frames, (shift, shift, shift, shift), mode="replicate").permute(0, 2, 3, 1)
    rows = torch.arange(height, device=frames.device)[None, :] + offsets[:, :1]
    cols = torch.arange(width, device=frames.device)[None, :] + offsets[:, 1:]
    batch = torch.arange(n, device=frames.device)[:, None, None]
    return padded[batch, rows[:, :, None], cols[:, None, :]].permute(0, 3, 1, 2)
