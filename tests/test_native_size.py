"""``JaxIP2PEditor.from_pretrained(folder)`` works at the folder's own size, as diffusers'
pipelines do (UNet ``sample_size`` x the VAE's scale factor), not at SD's 512 (issue 51)."""

from __future__ import annotations

import json

import pytest

from jaxedit.editors import DEFAULT_SIZE, bundled_editor, native_size


def _folder(root, unet: dict | None, vae: dict | None):
    for name, config in (("unet", unet), ("vae", vae)):
        if config is not None:
            (root / name).mkdir(parents=True)
            (root / name / "config.json").write_text(json.dumps(config))
    return root


@pytest.mark.parametrize("unet, vae, size", [
    ({"sample_size": 64}, {"block_out_channels": [128, 256, 512, 512], "sample_size": 768}, 512),
    ({"sample_size": 16}, {"block_out_channels": [16, 32, 64], "sample_size": 512}, 64),
    ({"sample_size": [12, 12]}, {"block_out_channels": [8, 16]}, 24),
    ({"sample_size": 16}, None, DEFAULT_SIZE),   # no VAE config: SD's size
    ({}, {"block_out_channels": [8, 16]}, DEFAULT_SIZE),   # the UNet states no size
])
def test_native_size_is_diffusers_default(tmp_path, unet, vae, size):
    assert native_size(_folder(tmp_path / "m", unet, vae)) == size


def test_from_pretrained_defaults_to_the_folders_size():
    from jaxedit.editors.jax_ip2p import JaxIP2PEditor

    folder = bundled_editor()
    unet = json.loads((folder / "unet" / "config.json").read_text())
    vae = json.loads((folder / "vae" / "config.json").read_text())
    want = unet["sample_size"] * 2 ** (len(vae["block_out_channels"]) - 1)
    editor = JaxIP2PEditor.from_pretrained(folder, steps=1)
    assert editor.size == want == 64 != DEFAULT_SIZE
    assert editor.model_hw(48, 48) == (64, 64)  # a 48 px view is edited at 64 px, not 512
    assert JaxIP2PEditor.from_pretrained(folder, size=32, steps=1).size == 32
