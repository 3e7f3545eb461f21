"""CLIP's text encoder (Stable Diffusion's conditioning) and its tokenizer, without torch;
pytree paths are the checkpoint's names without ``text_model.``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from .layers import Embedding, LayerNorm, Linear, activation, attention

Array = jax.Array

__all__ = ["CLIPTextEncoder", "CLIPTokenizer"]


class CLIPAttention(eqx.Module):
    """Multi-head causal self-attention with biased q/k/v/out projections (CLIP's names)."""

    q_proj: Linear
    k_proj: Linear
    v_proj: Linear
    out_proj: Linear
    heads: int = eqx.field(static=True)

    def __call__(self, x: Array) -> Array:
        """[B, L, D] -> [B, L, D]"""
        split = lambda t: t.reshape(*t.shape[:2], self.heads, -1)  # noqa: E731
        out = attention(split(self.q_proj(x)), split(self.k_proj(x)), split(self.v_proj(x)),
                        causal=True)
        return self.out_proj(out.reshape(x.shape[:2] + (-1,)))


class CLIPMLP(eqx.Module):
    fc1: Linear
    fc2: Linear
    act: str = eqx.field(static=True)

    def __call__(self, x: Array) -> Array:
        return self.fc2(activation(self.act)(self.fc1(x)))


class CLIPEncoderLayer(eqx.Module):
    self_attn: CLIPAttention
    layer_norm1: LayerNorm
    mlp: CLIPMLP
    layer_norm2: LayerNorm

    def __call__(self, x: Array) -> Array:
        x = x + self.self_attn(self.layer_norm1(x))
        return x + self.mlp(self.layer_norm2(x))


class CLIPEncoder(eqx.Module):
    layers: tuple[CLIPEncoderLayer, ...]


class CLIPEmbeddings(eqx.Module):
    token_embedding: Embedding
    position_embedding: Embedding


class CLIPTextEncoder(eqx.Module):
    """transformers' CLIPTextModel's ``last_hidden_state``."""

    embeddings: CLIPEmbeddings
    encoder: CLIPEncoder
    final_layer_norm: LayerNorm

    #: Checkpoint names carry this prefix (``text_model.encoder...``).
    CHECKPOINT_PREFIX = "text_model."

    @staticmethod
    def from_config(config: dict, *, key: jax.Array, dtype=jnp.float32) -> "CLIPTextEncoder":
        """Random weights in the architecture of a transformers ``CLIPTextConfig`` dict."""
        try:
            d, layers = int(config["hidden_size"]), int(config["num_hidden_layers"])
            heads, inner = int(config["num_attention_heads"]), int(config["intermediate_size"])
            vocab, positions = int(config["vocab_size"]), int(config["max_position_embeddings"])
        except (KeyError, TypeError, ValueError) as e:
            raise DataError("text_encoder/config.json", f"missing or bad entry {e}") from None
        act, eps = config.get("hidden_act", "quick_gelu"), float(config.get("layer_norm_eps", 1e-5))
        activation(act)  # refuses an unknown activation now, not at the first call
        k_tok, k_pos, *k_layers = jax.random.split(key, layers + 2)

        def layer(k):
            kq, kk, kv, ko, k1, k2 = jax.random.split(k, 6)
            lin = lambda kk_, a, b: Linear.init(kk_, a, b, dtype=dtype)  # noqa: E731
            return CLIPEncoderLayer(
                CLIPAttention(lin(kq, d, d), lin(kk, d, d), lin(kv, d, d), lin(ko, d, d), heads),
                LayerNorm.init(d, eps, dtype), CLIPMLP(lin(k1, d, inner), lin(k2, inner, d), act),
                LayerNorm.init(d, eps, dtype))

        return CLIPTextEncoder(
            CLIPEmbeddings(Embedding.init(k_tok, vocab, d, dtype),
                           Embedding.init(k_pos, positions, d, dtype)),
            CLIPEncoder(tuple(layer(k) for k in k_layers)), LayerNorm.init(d, eps, dtype))

    def __call__(self, input_ids: Array) -> Array:
        """input_ids int [B, L] (L <= max_position_embeddings) -> last_hidden_state [B, L, D]."""
        length = input_ids.shape[-1]
        x = (self.embeddings.token_embedding(input_ids)
             + self.embeddings.position_embedding.weight[:length])
        for layer in self.encoder.layers:
            x = layer(x)
        return self.final_layer_norm(x)


_CLIP_SPLIT = (r"""<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|"""
               r"""[^\s\p{L}\p{N}]+""")


def _token_text(value) -> str | None:
    """A special token as written in special_tokens_map / tokenizer_config: str or {"content"}."""
    if isinstance(value, dict):
        value = value.get("content")
    return value if isinstance(value, str) else None


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(path, f"unreadable JSON ({e})") from None
    if not isinstance(data, dict):
        raise DataError(path, "expected a JSON object")
    return data


#: The largest token id a vocabulary may hold (CLIP's is 49407).
MAX_VOCAB = 2_000_000


class CLIPTokenizer:
    """Prompts -> CLIP token ids int32 [B, max_length], as transformers' CLIPTokenizer padded
    and truncated to 77; immutable and compared by value, so a stable static jit field."""

    def __init__(self, tokenizer, *, bos_id: int, eos_id: int, pad_id: int, max_length: int):
        self._tokenizer = tokenizer
        self.bos_id, self.eos_id, self.pad_id, self.max_length = bos_id, eos_id, pad_id, max_length
        self._key = (tokenizer.to_str(), bos_id, eos_id, pad_id, max_length)

    def __eq__(self, other):
        return isinstance(other, CLIPTokenizer) and self._key == other._key

    def __hash__(self):
        return hash(self._key)

    @classmethod
    def from_folder(cls, folder: str | os.PathLike) -> "CLIPTokenizer":
        """Read a diffusers ``tokenizer/`` folder (``tokenizer.json``, else ``vocab.json`` +
        ``merges.txt``; special tokens and length from its configs, else CLIP's)."""
        from tokenizers import Regex, Tokenizer, decoders, normalizers, pre_tokenizers
        from tokenizers.models import BPE

        folder = Path(folder)
        settings: dict = {}
        for name in ("tokenizer_config.json", "special_tokens_map.json"):
            if (folder / name).is_file():
                settings.update({k: v for k, v in _read_json(folder / name).items()
                                 if v is not None})
        bos = _token_text(settings.get("bos_token")) or "<|startoftext|>"
        eos = _token_text(settings.get("eos_token")) or "<|endoftext|>"
        unk = _token_text(settings.get("unk_token")) or "<|endoftext|>"
        pad = _token_text(settings.get("pad_token")) or eos
        max_length = settings.get("model_max_length", 77)
        if not isinstance(max_length, int) or not 2 <= max_length <= 10_000:
            max_length = 77  # transformers writes a huge sentinel when the length is unset

        if (folder / "tokenizer.json").is_file():
            try:
                tok = Tokenizer.from_file(str(folder / "tokenizer.json"))
            except Exception as e:  # noqa: BLE001 - tokenizers raises a bare Exception
                raise DataError(folder / "tokenizer.json", f"unreadable tokenizer ({e})") from None
        else:
            vocab_path, merges_path = folder / "vocab.json", folder / "merges.txt"
            for p in (vocab_path, merges_path):
                if not p.is_file():
                    raise DataError(p, "missing (a CLIP tokenizer needs vocab.json and merges.txt, "
                                    "or tokenizer.json)")
            vocab = _read_json(vocab_path)
            if not all(isinstance(v, int) and not isinstance(v, bool) and 0 <= v < MAX_VOCAB
                       for v in vocab.values()) or len(set(vocab.values())) != len(vocab):
                raise DataError(vocab_path, f"must map each token to its own id in 0 .. "
                                            f"{MAX_VOCAB - 1}")
            try:
                lines = merges_path.read_text(encoding="utf-8").splitlines()
            except (OSError, UnicodeDecodeError) as e:
                raise DataError(merges_path, f"unreadable ({e})") from None
            merges = []
            for number, line in enumerate(lines, 1):
                if not line.strip() or (number == 1 and line.startswith("#version")):
                    continue
                parts = line.split()
                if len(parts) != 2:
                    raise DataError(merges_path, f"line {number} is not a pair of tokens: {line!r}")
                merges.append((parts[0], parts[1]))
            tok = Tokenizer(BPE(vocab=vocab, merges=merges, dropout=None, continuing_subword_prefix="",
                                end_of_word_suffix="</w>", fuse_unk=False, unk_token=unk))
            tok.normalizer = normalizers.Sequence(
                [normalizers.NFC(), normalizers.Replace(Regex(r"\s+"), " "), normalizers.Lowercase()])
            tok.pre_tokenizer = pre_tokenizers.Sequence([
                pre_tokenizers.Split(Regex(_CLIP_SPLIT), behavior="removed", invert=True),
                pre_tokenizers.ByteLevel(add_prefix_space=False)])
            tok.decoder = decoders.ByteLevel()
        tok.add_special_tokens(sorted({bos, eos, unk, pad}))
        tok.no_padding()
        tok.no_truncation()
        ids = {}
        for name, text in (("bos", bos), ("eos", eos), ("pad", pad)):
            ids[name] = tok.token_to_id(text)
            if ids[name] is None:
                raise DataError(folder, f"{name} token {text!r} is not in the vocabulary")
        return cls(tok, bos_id=ids["bos"], eos_id=ids["eos"], pad_id=ids["pad"],
                   max_length=max_length)

    def ids(self, prompts: str | list[str]) -> np.ndarray:
        """Prompt(s) -> int32 [B, max_length]: bos, at most max_length - 2 tokens, eos, pads."""
        prompts = [prompts] if isinstance(prompts, str) else list(prompts)
        out = np.full((len(prompts), self.max_length), self.pad_id, np.int32)
        for row, enc in enumerate(self._tokenizer.encode_batch(prompts, add_special_tokens=False)):
            body = enc.ids[: self.max_length - 2]
            seq = [self.bos_id, *body, self.eos_id]
            out[row, : len(seq)] = seq
        return out

    __call__ = ids
