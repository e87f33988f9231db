"""Training images kept as 8-bit codes on the device, a quarter of float32's memory, and expanded on use.

Most photos are 8-bit, and every image the loader serves from an 8-bit file (or from its 8-bit resize cache) holds
exactly the values k / 255 that `image_io` decodes to. Those images are kept as their codes and expanded through a
table of the decoder's own float32 values, so an expanded image is bit for bit the one that was loaded (a multiply by
1/255 differs from the division in the last bit for half the codes). Images with other values (16-bit files, RGBA
composited over a background) are kept as they are.
"""
from __future__ import annotations

from typing import Dict, Optional

import numpy as np
import torch

# What image_io decodes code k to: float32(k) / 255 (numpy rounds the division correctly in float32).
_DECODED = np.arange(256, dtype=np.uint8).astype(np.float32) / 255.0
_tables: Dict[torch.device, torch.Tensor] = {}


def _table(device: torch.device) -> torch.Tensor:
    table = _tables.get(device)
    if table is None:
        table = _tables[device] = torch.from_numpy(_DECODED).to(device)
    return table


def pack(image: torch.Tensor) -> Optional[torch.Tensor]:
    """The uint8 codes of a float32 image whose every value is an 8-bit code's decoded value, else None."""
    if image.dtype != torch.float32 or image.numel() == 0:
        return None
    codes = torch.round(image * 255.0).clamp_(0, 255).to(torch.uint8)
    return codes if torch.equal(unpack(codes), image) else None


def unpack(codes: torch.Tensor) -> torch.Tensor:
    """The float32 image of `pack`'s codes (the same values the loader produced)."""
    table = _table(codes.device)
    return table.index_select(0, codes.reshape(-1).to(torch.int32)).view(codes.shape)
