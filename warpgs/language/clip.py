"""Real language features with CLIP (optional extra `warpgs[clip]`: open-clip-torch + segment-anything).

Nothing is ever downloaded: both models load from checkpoint files already on disk, and a missing package or
file raises `ClipUnavailable` saying what to install or where to put the weights.

    from warpgs.language.clip import extract_scene_features
    extract_scene_features(scene, clip_checkpoint="ViT-B-16.bin", sam_checkpoint="sam_vit_h.pth")
    # -> <scene>/language_features/<stem>_s.npy + _f.npy, then train with configs/language.yaml and
    #    extensions.language.text_encoder=clip extensions.language.clip_checkpoint=ViT-B-16.bin

Segments are the "whole object" level: the automatic mask generator's masks taken largest first, each pixel
belonging to the largest mask that covers it (masks left with fewer than `min_area` pixels are dropped). Each
segment's feature is CLIP's image embedding of its bounding-box crop with the other pixels blacked out, padded
to a square (as LangSplat does), L2-normalised.
"""
from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from typing import Iterable, Optional, Sequence, Union

import numpy as np
import torch

from warpgs.language.features_io import FOLDER, save_view_features, write_feature_meta

INSTALL_HINT = "pip install 'warpgs[clip]' (open-clip-torch, segment-anything)"


class ClipUnavailable(RuntimeError):
    """The CLIP extra cannot run here: a package or a local weight file is missing."""


def _require(module: str, package: str):
    if importlib.util.find_spec(module) is None:
        raise ClipUnavailable(f"the {package!r} package is not installed ({INSTALL_HINT})")
    return importlib.import_module(module)


def _local_file(path, what: str) -> Path:
    if path is None:
        raise ClipUnavailable(f"{what}: no checkpoint file given; warpgs never downloads weights, pass the path "
                              f"of a local file")
    p = Path(path).expanduser()
    if not p.is_file():
        raise ClipUnavailable(f"{what}: checkpoint {p} not found (warpgs never downloads weights)")
    return p


def _device(device) -> torch.device:
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class ClipModel:
    """open_clip model + preprocessing + tokenizer from a local checkpoint."""

    def __init__(self, model_name: str = "ViT-B-16", checkpoint=None, device=None):
        open_clip = _require("open_clip", "open-clip-torch")
        ckpt = _local_file(checkpoint, f"CLIP {model_name}")
        self.device = _device(device)
        try:
            model, _, preprocess = open_clip.create_model_and_transforms(model_name, pretrained=str(ckpt))
            self.tokenizer = open_clip.get_tokenizer(model_name)
        except Exception as e:  # unknown architecture, mismatched weights, a tokenizer that would download
            raise ClipUnavailable(f"CLIP {model_name} from {ckpt}: {type(e).__name__}: {e}") from None
        self.model = model.to(self.device).eval()
        self.preprocess = preprocess
        self.model_name = model_name

    @torch.no_grad()
    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        tokens = self.tokenizer(list(texts)).to(self.device)
        return torch.nn.functional.normalize(self.model.encode_text(tokens).float(), dim=-1)

    @torch.no_grad()
    def encode_images(self, images: Sequence, batch_size: int = 64) -> torch.Tensor:
        """PIL images -> [n, C] unit embeddings."""
        out = []
        for i in range(0, len(images), batch_size):
            batch = torch.stack([self.preprocess(im) for im in images[i:i + batch_size]]).to(self.device)
            out.append(torch.nn.functional.normalize(self.model.encode_image(batch).float(), dim=-1))
        return torch.cat(out) if out else torch.zeros(0, 0)


class ClipTextEncoder:
    """The `encode(texts) -> [n, C]` interface of HashTextEncoder, backed by real CLIP weights."""

    name = "clip"

    def __init__(self, model_name: str = "ViT-B-16", checkpoint=None, device=None, clip: Optional[ClipModel] = None):
        self.clip = clip or ClipModel(model_name, checkpoint, device)

    def encode(self, texts: Union[str, Iterable[str]]) -> torch.Tensor:
        items = [texts] if isinstance(texts, str) else list(texts)
        return self.clip.encode_text(items).cpu()


def whole_level_segments(masks: Sequence[dict], shape, min_area: int = 100) -> list:
    """SAM mask records -> list of [H, W] bool masks, largest first, each keeping only pixels no larger mask
    took (a partition of the covered pixels into whole objects)."""
    taken = np.zeros(shape, bool)
    out = []
    for m in sorted(masks, key=lambda r: -int(r.get("area", np.count_nonzero(r["segmentation"])))):
        seg = np.asarray(m["segmentation"], bool) & ~taken
        if seg.sum() < min_area:
            continue
        taken |= seg
        out.append(seg)
    return out


def masked_crop(image: np.ndarray, mask: np.ndarray):
    """The mask's bounding box with other pixels black, padded to a square (PIL image)."""
    from PIL import Image

    rows, cols = np.nonzero(mask)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    crop = np.where(mask[r0:r1, c0:c1, None], image[r0:r1, c0:c1], 0)
    h, w = crop.shape[:2]
    side = max(h, w)
    square = np.zeros((side, side, 3), image.dtype)
    square[(side - h) // 2:(side - h) // 2 + h, (side - w) // 2:(side - w) // 2 + w] = crop
    return Image.fromarray(square)


def extract_scene_features(scene, *, clip_checkpoint, sam_checkpoint, clip_model: str = "ViT-B-16",
                           sam_model_type: str = "vit_h", out_folder=None, device=None, min_area: int = 100,
                           views=None, mask_generator_options: Optional[dict] = None) -> Path:
    """Write LangSplat-style whole-level CLIP features for the scene's views (see the module docstring)."""
    sam_pkg = _require("segment_anything", "segment-anything")
    sam_ckpt = _local_file(sam_checkpoint, f"SAM {sam_model_type}")
    clip = ClipModel(clip_model, clip_checkpoint, device)
    try:
        sam = sam_pkg.sam_model_registry[sam_model_type](checkpoint=str(sam_ckpt)).to(clip.device)
    except Exception as e:
        raise ClipUnavailable(f"SAM {sam_model_type} from {sam_ckpt}: {type(e).__name__}: {e}") from None
    generator = sam_pkg.SamAutomaticMaskGenerator(sam, **(mask_generator_options or {}))
    folder = Path(out_folder) if out_folder is not None else Path(scene.root) / FOLDER
    indices = range(len(scene)) if views is None else views
    dim = None
    for i in indices:
        rgb = (np.clip(scene.image_np(i)[0], 0, 1) * 255).round().astype(np.uint8)
        segments = whole_level_segments(generator.generate(rgb), rgb.shape[:2], min_area)
        seg_map = np.full(rgb.shape[:2], -1, np.int32)
        for k, m in enumerate(segments):
            seg_map[m] = k
        feats = clip.encode_images([masked_crop(rgb, m) for m in segments]).cpu().numpy() if segments else None
        if feats is None:
            dim = dim or 512
            feats = np.zeros((0, dim), np.float32)
        dim = feats.shape[1]
        save_view_features(folder, scene.cameras[i].name, seg_map, feats)
    meta = {"source": "clip", "text_encoder": "clip", "clip_model": clip_model, "clip_checkpoint": str(clip_checkpoint),
            "sam_model_type": sam_model_type, "dim": dim, "min_area": min_area}
    write_feature_meta(folder, meta)
    return folder
