"""Stage 8, CLIP similarity of crops (Table 1 of the paper).

Random square crops of turntable renders of the stylized scene and of the style scene are embedded
with an open_clip image encoder; the score is the mean cosine similarity over all (stylized crop,
style crop) pairs, in percent:

    CLIP-sim = 100 * mean_ij <e_i, f_j> = 100 * <mean_i e_i, mean_j f_j>,   |e_i| = |f_j| = 1.

Crops: ``count`` windows of ``size`` x ``size`` pixels drawn uniformly (view, x, y) by a
``torch.Generator`` seeded with ``seed``, kept only when their mean alpha is at least ``min_alpha`` (so
crops show the object, not the background), composited on white, resized (bicubic, antialiased) to the
encoder's input size and normalized with the model's mean/std.

Weights come only from a local file (``checkpoint``; open_clip accepts a path as ``pretrained``); no
download is ever attempted (``HF_HUB_OFFLINE=1``, and a checkpoint that is not an existing file is
reported, not fetched). Without one, the metric is "not computed" with the reason.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from .device import resolve_device
from .options import checked, option

log = logging.getLogger(__name__)


@dataclass
@checked("crops")
class CropConfig:
    count: int = option(32, "crops per render set", minimum=1)
    size: int = option(64, "crop side in pixels", minimum=4)
    min_alpha: float = option(0.5, "minimum mean alpha of a crop", minimum=0, maximum=1)
    seed: int = option(0, "seed of the crop positions")



@dataclass
@checked("clip")
class ClipConfig:
    """model: an open_clip architecture name (or the name of ``model_config``); checkpoint: local weights
    file (None: CLIP is not computed); model_config: optional JSON file with an open_clip model config
    ({"embed_dim", "vision_cfg", "text_cfg"}), registered under its file stem; device: "auto" | "cpu" |
    "cuda"; batch: crops per forward pass."""

    model: str = option("ViT-B-32", "open_clip architecture")
    checkpoint: str | None = option(None, "a local weights file (null: CLIP is reported as not computed)")
    model_config: str | None = option(None, "optional JSON architecture for a model open_clip does not know")
    device: str = option("auto", "auto: CUDA when available", enum=["auto", "cpu", "cuda"])
    batch: int = option(64, "crops per forward pass", minimum=1)


class ClipUnavailable(RuntimeError):
    """CLIP cannot be computed here; the message is the reason reported in the table."""


def random_crops(frames: torch.Tensor, cfg: CropConfig, background=(1.0, 1.0, 1.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """Deterministic (by ``cfg.seed``) foreground crops of RGBA frames.

    frames: [V, H, W, 4] straight alpha in [0, 1] -> crops [n, size, size, 3] (composited on
    ``background``) and boxes [n, 3] (view, y0, x0). ``n < cfg.count`` only when the frames have too
    little foreground (logged).
    """
    V, H, W, _ = frames.shape
    s = cfg.size
    if s > H or s > W:
        raise ValueError(f"crops: crop size {s} exceeds the frame size {H}x{W}")
    g = torch.Generator().manual_seed(cfg.seed)
    # integral image of alpha: mean alpha of every candidate window in O(1)
    a = F.pad(frames[..., 3].double(), (1, 0, 1, 0)).cumsum(1).cumsum(2)
    boxes = []
    for _ in range(50):
        m = 8 * cfg.count
        v = torch.randint(0, V, (m,), generator=g)
        y = torch.randint(0, H - s + 1, (m,), generator=g)
        x = torch.randint(0, W - s + 1, (m,), generator=g)
        mean_a = (a[v, y + s, x + s] - a[v, y, x + s] - a[v, y + s, x] + a[v, y, x]) / (s * s)
        ok = mean_a >= cfg.min_alpha
        boxes += torch.stack([v, y, x], 1)[ok].tolist()
        if len(boxes) >= cfg.count:
            break
    boxes = torch.tensor(boxes[:cfg.count], dtype=torch.long).reshape(-1, 3)
    if len(boxes) < cfg.count:
        log.warning("crops: only %d of %d crops have mean alpha >= %.2f", len(boxes), cfg.count, cfg.min_alpha)
    if len(boxes) == 0:
        raise ValueError("crops: the renders have no foreground (empty scene, or the cameras miss it)")
    bg = torch.as_tensor(background, dtype=frames.dtype)
    crops = torch.stack([frames[v, y:y + s, x:x + s] for v, y, x in boxes.tolist()])
    return crops[..., :3] * crops[..., 3:] + (1 - crops[..., 3:]) * bg, boxes


def load_clip(cfg: ClipConfig):
    """The open_clip model of ``cfg`` in eval mode, weights from ``cfg.checkpoint``; raises
    :class:`ClipUnavailable` with the reason when it cannot be had without a download."""
    if not cfg.checkpoint:
        raise ClipUnavailable("no clip.checkpoint configured (weights are never downloaded)")
    ckpt = Path(cfg.checkpoint).expanduser()
    if not ckpt.is_file():
        raise ClipUnavailable(f"clip.checkpoint {ckpt} is not a file")
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    try:
        import open_clip
    except ImportError as e:  # pragma: no cover - a dependency
        raise ClipUnavailable(f"open_clip is not importable ({e})") from None
    if cfg.model_config:
        path = Path(cfg.model_config).expanduser()
        if not path.is_file():
            raise ValueError(f"clip.model_config: {path} is not a file")
        open_clip.add_model_config(path)
    if open_clip.get_model_config(cfg.model) is None:
        raise ValueError(f"clip.model: unknown open_clip architecture '{cfg.model}'")
    try:
        model = open_clip.create_model(cfg.model, pretrained=str(ckpt), device="cpu", pretrained_text=False)
    except Exception as e:  # torch.load / load_state_dict raise many types on a bad file
        raise ValueError(f"{ckpt}: cannot load it as '{cfg.model}' weights ({str(e).splitlines()[0][:300]})") from None
    return model.eval()


@torch.no_grad()
def embed(model, crops: torch.Tensor, batch: int = 64, device: str = "auto") -> torch.Tensor:
    """crops [n, h, w, 3] in [0, 1] -> unit image embeddings [n, D] (float64)."""
    dev = resolve_device(device)
    model = model.to(dev)
    pcfg = getattr(model.visual, "preprocess_cfg", {}) or {}
    from open_clip.constants import OPENAI_DATASET_MEAN, OPENAI_DATASET_STD

    mean = torch.tensor(pcfg.get("mean", OPENAI_DATASET_MEAN), device=dev)[:, None, None]
    std = torch.tensor(pcfg.get("std", OPENAI_DATASET_STD), device=dev)[:, None, None]
    size = model.visual.image_size
    size = tuple(size) if isinstance(size, (tuple, list)) else (size, size)
    out = []
    for i in range(0, len(crops), batch):
        x = crops[i:i + batch].permute(0, 3, 1, 2).float().to(dev)
        x = F.interpolate(x, size=size, mode="bicubic", antialias=True, align_corners=False).clamp(0, 1)
        e = model.encode_image((x - mean) / std).double()
        out.append(e / e.norm(dim=-1, keepdim=True).clamp_min(1e-12))
    return torch.cat(out).cpu()


def clip_similarity(model, crops_a: torch.Tensor, crops_b: torch.Tensor, batch: int = 64, device: str = "auto") -> float:
    """100 x mean cosine similarity over all pairs of crops (see the module docstring)."""
    ea, eb = embed(model, crops_a, batch, device), embed(model, crops_b, batch, device)
    return float(100.0 * (ea @ eb.T).mean())
