"""Stable Diffusion 1.x / InstructPix2Pix networks as equinox modules, loaded without torch
(:func:`load_ip2p` reads a diffusers folder into :class:`IP2PModels`)."""

from .clip_text import CLIPTextEncoder, CLIPTokenizer
from .load import (DDPMSchedule, IP2PModels, cast, check_layout, load_ip2p, load_module,
                   module_from_tensors, read_weights)
from .layers import set_query_chunk
from .unet import UNet2DCondition
from .vae import AutoencoderKL

__all__ = ["AutoencoderKL", "CLIPTextEncoder", "CLIPTokenizer", "DDPMSchedule", "IP2PModels",
           "UNet2DCondition", "cast", "check_layout", "load_ip2p", "load_module",
           "module_from_tensors", "read_weights", "set_query_chunk"]
