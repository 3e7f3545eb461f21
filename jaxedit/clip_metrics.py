"""Instruct-NeRF2NeRF's CLIP edit metrics over rendered test-view sequences: with unit CLIP
embeddings, dI_k = I(x_k) - I(o_k) (edited, original view k) and dT = T(c_x) - T(c_o)
(captions), direction similarity = mean_k cos(dI_k, dT) and consistency = mean_k
cos(dI_k, dI_{k+1}); a vanishing direction's NaN is skipped (counted as ``undefined``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .errors import DataError
from .io.weights import local_model_folder

__all__ = ["ClipEncoder", "DEFAULT_CLIP", "direction_metrics", "load_clip_metrics"]

DEFAULT_CLIP = "openai/clip-vit-large-patch14"
HOW_TO_GET = (f"a CLIP model in transformers format ({DEFAULT_CLIP} as IN2N, or "
              f"openai/clip-vit-base-patch32); download it on a machine with network with "
              f"`huggingface-cli download {DEFAULT_CLIP} --local-dir DIR` and give "
              f"that folder as the CLIP weights")

# OpenAI CLIP's normalisation, used when the folder has no preprocessor_config.json.
_CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
_CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _cos(a: np.ndarray, b: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """Row-wise cosine; NaN where either vector is (numerically) zero."""
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    ok = (na > eps) & (nb > eps)
    out = np.full(na.shape, np.nan)
    out[ok] = np.sum(a[ok] * b[ok], axis=-1) / (na[ok] * nb[ok])
    return np.clip(out, -1.0, 1.0)


def _mean(values: np.ndarray) -> float:
    defined = values[np.isfinite(values)]
    return float(defined.mean()) if defined.size else float("nan")


def direction_metrics(image_orig, image_edit, text_orig, text_edit) -> dict:
    """IN2N's CLIP metrics of image embeddings float [N, D] of N views in path order and
    text embeddings float [D]: the two means, their per-view / per-pair values,
    ``clip_score_edit``, ``image_similarity`` and the undefined counts."""
    io, ie = np.asarray(image_orig, np.float64), np.asarray(image_edit, np.float64)
    to, te = np.asarray(text_orig, np.float64), np.asarray(text_edit, np.float64)
    if io.ndim != 2 or io.shape != ie.shape:
        raise DataError("images", f"original and edited embeddings must both be [N, D]; got "
                        f"{io.shape} and {ie.shape}")
    if to.shape != (io.shape[1],) or te.shape != to.shape:
        raise DataError("captions", f"caption embeddings must be [{io.shape[1]}]; got "
                        f"{to.shape} and {te.shape}")
    if io.shape[0] < 1:
        raise DataError("images", "no views")
    io, ie, to, te = _unit(io), _unit(ie), _unit(to), _unit(te)
    d_img = ie - io
    d_txt = te - to
    per_view = _cos(d_img, np.broadcast_to(d_txt, d_img.shape))
    per_pair = _cos(d_img[:-1], d_img[1:]) if len(d_img) > 1 else np.zeros((0,))
    return {
        "direction_similarity": _mean(per_view),
        "direction_consistency": _mean(per_pair),
        "clip_score_edit": float(np.mean(ie @ te)),
        "image_similarity": float(np.mean(np.sum(io * ie, axis=-1))),
        "per_view_direction_similarity": per_view.tolist(),
        "per_pair_direction_consistency": per_pair.tolist(),
        "views": int(len(d_img)),
        "undefined": {"direction_similarity": int(np.sum(~np.isfinite(per_view))),
                      "direction_consistency": int(np.sum(~np.isfinite(per_pair)))},
    }


def _resolve(path) -> Path:
    p = local_model_folder(path, what="CLIP weights", how_to_get=HOW_TO_GET)
    if not (p / "config.json").is_file():
        raise DataError(p, f"no config.json: not a transformers model folder; needs {HOW_TO_GET}")
    if not any((p / f).is_file() for f in ("vocab.json", "tokenizer.json")):
        raise DataError(p, f"no tokenizer files (vocab.json + merges.txt or tokenizer.json); "
                        f"needs {HOW_TO_GET}")
    return p


class ClipEncoder:
    """A local CLIP model giving unit-normalised image and text embeddings (NumPy float32)."""

    def __init__(self, model, tokenizer, *, mean=_CLIP_MEAN, std=_CLIP_STD, crop=None,
                 device=None, dtype=None, source: str = ""):
        import torch

        self.torch = torch
        self.device = torch.device(device or ("cuda:0" if torch.cuda.is_available() else "cpu"))
        self.dtype = dtype or (torch.float32 if self.device.type == "cpu" else torch.float16)
        self.model = model.to(self.device, self.dtype).eval().requires_grad_(False)
        self.tokenizer = tokenizer
        self.crop = int(crop or model.config.vision_config.image_size)
        self.mean = torch.tensor(mean, dtype=torch.float32, device=self.device)[:, None, None]
        self.std = torch.tensor(std, dtype=torch.float32, device=self.device)[:, None, None]
        self.source = source

    @classmethod
    def from_pretrained(cls, path=DEFAULT_CLIP, *, device=None, dtype=None) -> "ClipEncoder":
        """Load a transformers CLIPModel + tokenizer from a local folder (or the local HF cache)."""
        try:
            from transformers import CLIPModel, CLIPTokenizer
        except ImportError as e:
            raise ImportError("CLIP metrics need torch and transformers: pip install "
                              "'jaxedit[ip2p]'") from e
        root = _resolve(path)
        try:
            model = CLIPModel.from_pretrained(root, local_files_only=True)
            tokenizer = CLIPTokenizer.from_pretrained(root, local_files_only=True)
        except (OSError, ValueError) as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise DataError(root, f"cannot load CLIP ({first}); needs {HOW_TO_GET}") from None
        mean, std, crop = _CLIP_MEAN, _CLIP_STD, None
        pre = root / "preprocessor_config.json"
        if pre.is_file():
            try:
                cfg = json.loads(pre.read_text())
            except json.JSONDecodeError:
                raise DataError(pre, "malformed JSON") from None
            mean, std = cfg.get("image_mean", mean), cfg.get("image_std", std)
            c = cfg.get("crop_size")
            crop = c.get("height") if isinstance(c, dict) else c
        return cls(model, tokenizer, mean=mean, std=std, crop=crop, device=device, dtype=dtype,
                   source=str(root))

    def _preprocess(self, images):
        """float [N, H, W, 3] in [0, 1] -> normalised [N, 3, crop, crop] on the device."""
        torch = self.torch
        F = torch.nn.functional
        x = torch.as_tensor(np.ascontiguousarray(images, dtype=np.float32)).to(self.device)
        if x.ndim == 3:
            x = x[None]
        if x.ndim != 4 or x.shape[-1] != 3:
            raise DataError("images", f"expected float images [N, H, W, 3], got {tuple(x.shape)}")
        x = x.permute(0, 3, 1, 2)
        h, w = x.shape[-2:]
        scale = self.crop / min(h, w)
        size = (max(self.crop, round(h * scale)), max(self.crop, round(w * scale)))
        x = F.interpolate(x, size=size, mode="bicubic", align_corners=False, antialias=True)
        top, left = (size[0] - self.crop) // 2, (size[1] - self.crop) // 2
        x = x[..., top:top + self.crop, left:left + self.crop].clamp(0, 1)
        return ((x - self.mean) / self.std).to(self.dtype)

    @staticmethod
    def _features(out):
        # transformers < 5 returns the projected tensor, >= 5 an output whose pooler_output it is.
        return out if hasattr(out, "float") else out.pooler_output

    def encode_images(self, images, batch_size: int = 16) -> np.ndarray:
        """float [N, H, W, 3] in [0, 1] -> unit-normalised float32 [N, D]."""
        out = []
        with self.torch.inference_mode():
            for i in range(0, len(images), batch_size):
                pixels = self._preprocess(images[i:i + batch_size])
                out.append(self._features(self.model.get_image_features(pixel_values=pixels)).float())
        feats = self.torch.cat(out).cpu().numpy()
        return _unit(feats).astype(np.float32)

    def encode_texts(self, texts: list[str]) -> np.ndarray:
        """Captions -> unit-normalised float32 [M, D]."""
        with self.torch.inference_mode():
            tok = self.tokenizer(list(texts), padding=True, truncation=True, return_tensors="pt")
            out = self.model.get_text_features(input_ids=tok.input_ids.to(self.device),
                                               attention_mask=tok.attention_mask.to(self.device))
            feats = self._features(out).float().cpu().numpy()
        return _unit(feats).astype(np.float32)

    def edit_metrics(self, originals, edits, caption_orig: str, caption_edit: str) -> dict:
        """:func:`direction_metrics` of renders float [N, H, W, 3], original and edited."""
        if len(originals) != len(edits):
            raise DataError("images", f"{len(originals)} original renders but {len(edits)} edited")
        t = self.encode_texts([caption_orig, caption_edit])
        result = direction_metrics(self.encode_images(originals), self.encode_images(edits),
                                   t[0], t[1])
        result.update(clip_model=self.source, caption_orig=caption_orig, caption_edit=caption_edit)
        return result


def load_clip_metrics(path=DEFAULT_CLIP, *, device=None):
    """Factory for the runner: a callable (originals, edits, caption_orig, caption_edit) -> dict."""
    return ClipEncoder.from_pretrained(path, device=device).edit_metrics
