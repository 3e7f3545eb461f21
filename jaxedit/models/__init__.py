"""Stable Diffusion 1.x / InstructPix2Pix networks as equinox modules, loaded from diffusers
folders without torch.

- :class:`UNet2DCondition` (``unet.py``): eps(sample, timestep, text context), NHWC.
- :class:`AutoencoderKL` (``vae.py``): ``encode`` -> (mean, logvar), ``decode``.
- :class:`CLIPTextEncoder` and :class:`CLIPTokenizer` (``clip_text.py``).
- :func:`load_ip2p` (``load.py``): a diffusers folder -> :class:`IP2PModels`; :func:`cast`.
- :func:`set_query_chunk`: attention over query chunks (bounded memory at 512 px).

Layers and their checkpoint names: ``layers.py``. Importing this package needs jax,
equinox, numpy, safetensors and tokenizers only (tokenizers on first use).
"""

from .clip_text import CLIPTextEncoder, CLIPTokenizer
from .load import (DDPMSchedule, IP2PModels, cast, check_layout, load_ip2p, load_module,
                   module_from_tensors, read_weights)
from .layers import set_query_chunk
from .unet import UNet2DCondition
from .vae import AutoencoderKL

__all__ = ["AutoencoderKL", "CLIPTextEncoder", "CLIPTokenizer", "DDPMSchedule", "IP2PModels",
           "UNet2DCondition", "cast", "check_layout", "load_ip2p", "load_module",
           "module_from_tensors", "read_weights", "set_query_chunk"]
