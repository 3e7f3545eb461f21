"""The small InstructPix2Pix: its dataset, its export, its training command and the bundled
weights (jaxedit.editors, jaxedit_lab.train_editor, experiments/train_editor.py).

The whole training run is the CLI's ``--smoke`` (a couple of minutes: compiling the UNet's
step dominates); the bundled folder is checked against diffusers where torch is installed.
"""

from __future__ import annotations

import collections
import dataclasses
import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import cli
from jaxedit.editors.jax_ip2p import JaxIP2PEditor
from jaxedit.editors import bundled_editor, instructions, native_size
from jaxedit.errors import DataError
from jaxedit_lab.train_editor import edit_data, tiny_ip2p
from jaxedit_lab.train_editor.export import module_tensors, write_pipeline
from jaxedit.models import load_ip2p


def test_the_instructions_cover_what_the_editor_must_learn():
    kinds = [(i.kind, len(i.outcomes)) for i in edit_data.INSTRUCTIONS]
    single = [k for k, n in kinds if n == 1 and k in ("colour", "material")]
    divergent = [n for _, n in kinds if n > 1]
    assert len(edit_data.INSTRUCTIONS) >= 6 and len(single) >= 2
    assert len(divergent) >= 2 and min(divergent) >= 3
    assert ("local", 1) in kinds and ("geometry", 1) in kinds


def test_the_local_edit_changes_the_shirt_only():
    """One ray per pixel: the re-rendered view differs exactly where the shirt is seen."""
    from jaxedit.scenes import get_scene, render_scene, rig_cameras, surface_points_and_ids

    scene = get_scene("face")
    cams = rig_cameras(scene.rig, 3, width=24)
    edited = edit_data._edited_scene(scene, "make his shirt blue")
    before = render_scene(scene, cams, supersample=1)
    after = render_scene(edited, cams, supersample=1)
    _, ids, _ = surface_points_and_ids(scene, cams)
    shirt = ids == scene.object_names.index("shoulders")
    changed = np.abs(after - before).max(-1) > 1e-6
    assert shirt.any() and changed[shirt].mean() > 0.9
    assert not changed[~shirt].any()


# slow tier: renders the whole shipped dataset and scores every held-out view with LPIPS
@pytest.mark.slow
def test_divergent_outcomes_are_separated_and_as_far_from_the_original():
    from jaxedit.edit.difficulty import default_distance

    # The shipped dataset's own held-out views (its cameras are those of the defaults).
    cfg = tiny_ip2p.EditorTrainConfig()
    data = edit_data.build_dataset(cfg.size, cfg.procedural_views, cfg.scenes)
    views = np.flatnonzero(data.held_out)
    for prompt, s in edit_data.separation(data, default_distance("auto"), views).items():
        assert s["separated"], (prompt, s)
        assert max(s["to_original"]) < 1.5 * min(s["to_original"]), (prompt, s)


def test_an_outcome_is_a_function_of_the_colour_only():
    """The same colour gives the same edit wherever it is (so views agree)."""
    rgb = np.random.default_rng(0).uniform(size=(8, 8, 3)).astype(np.float32)
    moved = np.roll(rgb, (3, 5), axis=(0, 1))
    for (prompt, outcome) in edit_data.IMAGE_OUTCOMES:
        a = edit_data.apply_image_outcome(prompt, outcome, rgb, np.ones((8, 8)), (0.3, 0.6))
        b = edit_data.apply_image_outcome(prompt, outcome, moved, np.ones((8, 8)), (0.3, 0.6))
        np.testing.assert_array_equal(np.roll(a, (3, 5), axis=(0, 1)), b)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """Random networks of the smoke architecture written as a diffusers folder."""
    cfg = tiny_ip2p.EditorTrainConfig.smoke()
    vocab, merges = tiny_ip2p.train_tokenizer([i.prompt for i in edit_data.INSTRUCTIONS])
    bos, eos = vocab[tiny_ip2p.BOS], vocab[tiny_ip2p.EOS]
    unet, text = tiny_ip2p.build_networks(cfg, len(vocab), bos, eos, jax.random.key(1))
    vae = tiny_ip2p.AutoencoderKL.from_config(tiny_ip2p.vae_config(cfg), key=jax.random.key(2))
    out = write_pipeline(
        tmp_path_factory.mktemp("pipe") / "model", unet=unet,
        unet_config=tiny_ip2p.unet_config(cfg), vae=vae,
        vae_config=tiny_ip2p.vae_config(cfg, 0.5), text_encoder=text,
        text_config=tiny_ip2p.text_config(cfg, len(vocab), bos, eos), vocab=vocab,
        merges=merges, bos=tiny_ip2p.BOS, eos=tiny_ip2p.EOS, max_length=tiny_ip2p.MAX_LENGTH,
        scheduler_config=tiny_ip2p.SCHEDULER_CONFIG,
        instructions=[i.describe() for i in edit_data.INSTRUCTIONS])
    return out, (unet, vae, text)


def test_the_written_folder_loads_back_bit_for_bit(written):
    folder, (unet, vae, text) = written
    models = load_ip2p(folder)
    for ours, back in ((unet, models.unet), (vae, models.vae), (text, models.text_encoder)):
        a, b = module_tensors(ours), module_tensors(back)
        assert a.keys() == b.keys()
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert [i["prompt"] for i in instructions(folder)] == [
        i.prompt for i in edit_data.INSTRUCTIONS]


def test_the_tokenizer_reads_the_same_in_transformers(written):
    transformers = pytest.importorskip("transformers")
    folder, _ = written
    theirs = transformers.CLIPTokenizer.from_pretrained(folder / "tokenizer")
    ours = load_ip2p(folder).tokenizer
    for text in ["", *[i.prompt for i in edit_data.INSTRUCTIONS], "Make it  BLUE, please!",
                 "an unseen word: zebra"]:
        expected = theirs(text, padding="max_length", max_length=77, truncation=True).input_ids
        assert ours([text])[0].tolist() == expected, text


def _main(argv, capfd):
    code = cli.main([str(a) for a in argv])
    return code, capfd.readouterr()


@pytest.mark.slow
def test_train_editor_smoke_writes_a_working_editor_and_resumes(tmp_path, capfd):
    out = tmp_path / "run"
    code, _ = _main(["train-editor", "--smoke", "--out", out, "--quiet"], capfd)
    assert code == 0
    summary = json.loads((out / "training.json").read_text())
    assert summary["dataset"]["held_out_views"] > 0
    editor = JaxIP2PEditor.from_pretrained(out / "model", size=32, steps=2)
    assert editor.latent_factor == 4
    view = np.full((32, 32, 3), 0.5, np.float32)
    edited = editor.edit(view, view, editor.encode("make it black and white"), jax.random.key(0))
    assert edited.shape == (32, 32, 3) and bool(jnp.isfinite(edited).all())
    listed = json.loads((out / "model" / "instructions.json").read_text())
    assert listed["dataset"]["size"] == 32

    # A second run into the same folder must say --resume; a resumed finished run is a no-op.
    code, err = _main(["train-editor", "--smoke", "--out", out, "--quiet"], capfd)
    assert code == 2 and err.err.count("\n") == 1 and "--resume" in err.err
    before = (out / "model" / "unet" / "diffusion_pytorch_model.safetensors").read_bytes()
    code, _ = _main(["train-editor", "--smoke", "--out", out, "--resume", "--quiet"], capfd)
    assert code == 0
    assert (out / "model" / "unet" / "diffusion_pytorch_model.safetensors").read_bytes() == before

    # A corrupt checkpoint on resume: one line, exit 2, and the checkpoint is left as it was.
    (out / "checkpoints" / "unet.npz").write_bytes(b"not a checkpoint")
    code, err = _main(["train-editor", "--smoke", "--out", out, "--resume", "--quiet"], capfd)
    errors = [line for line in err.err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and "unet.npz" in errors[0], err.err
    assert err.err.splitlines()[-1] == errors[0]  # the stages done before it logged a line each
    assert (out / "checkpoints" / "unet.npz").read_bytes() == b"not a checkpoint"

    # --init: a run continued from the written folder keeps its autoencoder bit for bit, trains
    # its UNet on, and refuses a folder of another architecture before any work.
    more = tmp_path / "more"
    cfg = dataclasses.replace(tiny_ip2p.EditorTrainConfig.smoke(), init=str(out / "model"))
    from jaxedit_lab.train_editor import train_editor

    train_editor(cfg, more)
    vae = "vae/diffusion_pytorch_model.safetensors"
    assert (more / "model" / vae).read_bytes() == (out / "model" / vae).read_bytes()
    unet = "unet/diffusion_pytorch_model.safetensors"
    assert (more / "model" / unet).read_bytes() != (out / "model" / unet).read_bytes()
    with pytest.raises(DataError, match="--init"):
        train_editor(dataclasses.replace(cfg, text_width=16), tmp_path / "other")
    assert not (tmp_path / "other" / "checkpoints").exists()

    # --decoder-steps with --steps 0: only the decoder learns. The encoder (so the latents the
    # UNet was trained on), the UNet, the text encoder and the scaling factor stay --init's.
    sharp = tmp_path / "sharp"
    train_editor(dataclasses.replace(cfg, decoder_steps=3, steps=0), sharp)
    for part in (unet, "text_encoder/model.safetensors"):
        assert (sharp / "model" / part).read_bytes() == (out / "model" / part).read_bytes()
    old, new = (module_tensors(load_ip2p(f / "model").vae) for f in (out, sharp))
    frozen = [k for k in old if k.startswith(("encoder.", "quant_conv."))]
    assert frozen and all(np.array_equal(old[k], new[k]) for k in frozen)
    assert not all(np.array_equal(old[k], new[k]) for k in old if k.startswith("decoder."))
    configs = [json.loads((f / "model" / "vae" / "config.json").read_text()) for f in (out, sharp)]
    assert configs[0]["scaling_factor"] == configs[1]["scaling_factor"]
    assert json.loads((sharp / "training.json").read_text())["seconds"].keys() == {
        "dataset", "vae"}
    before = (sharp / "model" / vae).read_bytes()
    train_editor(dataclasses.replace(cfg, decoder_steps=3, steps=0), sharp, resume=True)
    assert (sharp / "model" / vae).read_bytes() == before


@pytest.mark.parametrize("flags, named", [({"decoder_steps": 3}, "--decoder-steps"),
                                          ({"steps": 0}, "--steps")])
def test_the_decoder_alone_or_a_kept_unet_needs_init(flags, named):
    with pytest.raises(DataError, match=named):
        dataclasses.replace(tiny_ip2p.EditorTrainConfig.smoke(), **flags).check()


@pytest.mark.parametrize("empty_is_identity", [True, False])
def test_the_empty_prompt_with_the_image_keeps_the_view(empty_is_identity):
    """IP2P's text dropout: with empty_is_identity an example whose text alone is dropped
    takes its input as target (E("") + image means "keep the view"); without, its edit."""
    v, m, hw = 6, 12, (2, 2, 4)
    # Latents as labels: input view v is v + 1, target row r is 100 + r (no posterior noise).
    inputs = np.stack([np.full(hw, v_ + 1.0, np.float32) for v_ in range(v)])
    d = tiny_ip2p.UNetData(
        target_mean=jnp.asarray(np.stack([np.full(hw, 100.0 + r, np.float32) for r in range(m)])),
        target_std=jnp.zeros((m, *hw)), input_mean=jnp.asarray(np.stack([inputs] * 2, 1)),
        input_std=jnp.zeros((v, *hw)), rows=jnp.arange(m, dtype=jnp.int32).reshape(2, 6),
        counts=jnp.asarray([6, 6], jnp.int32), active=jnp.asarray([0, 1], jnp.int32),
        views=jnp.arange(v, dtype=jnp.int32), tokens=jnp.asarray([[1, 2], [3, 4], [0, 0]]),
        target_view=jnp.asarray(np.arange(m) % v, jnp.int32),
        siblings=jnp.arange(m, dtype=jnp.int32)[:, None], outcomes=jnp.ones(m, jnp.int32))
    cfg = dataclasses.replace(tiny_ip2p.EditorTrainConfig.smoke(), batch=512, drop=0.3,
                              identity_share=0.0, degrade=0.0,
                              empty_is_identity=empty_is_identity)
    target, cond, tokens = tiny_ip2p.draw_batch(d, jax.random.key(0), cfg, 1.0)
    target, cond, tokens = (np.asarray(a)[:, 0, 0, 0] if a.ndim == 4 else np.asarray(a)
                            for a in (target, cond, tokens))
    empty = (tokens == 0).all(1)
    text_dropped = empty & (cond > 0)  # the image kept
    assert text_dropped.sum() > 50 and (~empty).sum() > 50
    assert (target[~empty] >= 100).all()  # an instruction: its edit
    if empty_is_identity:
        np.testing.assert_array_equal(target[text_dropped], cond[text_dropped])
    else:
        assert (target[text_dropped] >= 100).all()


def test_an_outcome_read_from_the_noise_is_uniform_and_is_the_noise_s():
    """outcome_of_noise: each of K outcomes 1/K of the draws; the bin follows the noise's
    checkerboard projection alone (adding a smooth latent, constant over pixels, leaves it)."""
    noise = jax.random.normal(jax.random.key(0), (30_000, 4, 4, 4))
    for k in (1, 2, 3):
        got = np.asarray(tiny_ip2p.outcome_of_noise(noise, jnp.full(len(noise), k)))
        np.testing.assert_allclose(np.bincount(got, minlength=k) / len(got), 1 / k, atol=0.01)
    three = jnp.full(len(noise), 3)
    got = tiny_ip2p.outcome_of_noise(noise, three)
    np.testing.assert_array_equal(tiny_ip2p.outcome_of_noise(noise + 5.0, three), got)
    np.testing.assert_array_equal(tiny_ip2p.outcome_of_noise(-noise, three), 2 - got)


def test_a_divergent_example_s_target_is_the_outcome_its_noise_stands_for():
    """With outcome_from_noise the drawn row is swapped for its sibling of the noise's
    outcome: rows of a (view, instruction) grouped in outcome order, single ones alone."""
    # rows: view 0 instruction 0 outcomes (2, 0, 1); view 1 instruction 0 outcomes (0, 1, 2);
    # view 0 instruction 1 (one outcome)
    view, ins, outcome = (np.array(a) for a in ([0, 0, 0, 1, 1, 1, 0], [0, 0, 0, 0, 0, 0, 1],
                                                [2, 0, 1, 0, 1, 2, 0]))
    siblings, counts = tiny_ip2p.outcome_siblings(view, ins, outcome, 3)
    np.testing.assert_array_equal(siblings[:6], [[1, 2, 0]] * 3 + [[3, 4, 5]] * 3)
    np.testing.assert_array_equal(siblings[6], [6, 6, 6])
    np.testing.assert_array_equal(counts, [3, 3, 3, 3, 3, 3, 1])
    hw = (4, 4, 4)
    d = tiny_ip2p.UNetData(  # latents as labels: target row r is 100 + r
        target_mean=jnp.asarray(np.stack([np.full(hw, 100.0 + r, np.float32)
                                          for r in range(7)])),
        target_std=jnp.zeros((7, *hw)), input_mean=jnp.zeros((2, 2, *hw)),
        input_std=jnp.zeros((2, *hw)), rows=jnp.asarray([[0, 1, 2, 3, 4, 5], [6] * 6]),
        counts=jnp.asarray([6, 1], jnp.int32), active=jnp.asarray([0, 1], jnp.int32),
        views=jnp.arange(2, dtype=jnp.int32), tokens=jnp.asarray([[1, 2], [3, 4], [0, 0]]),
        target_view=jnp.asarray(view, jnp.int32), siblings=jnp.asarray(siblings),
        outcomes=jnp.asarray(counts))
    cfg = dataclasses.replace(tiny_ip2p.EditorTrainConfig.smoke(), batch=600, drop=0.0,
                              identity_share=0.0, degrade=0.0, outcome_from_noise=True)
    noise = jax.random.normal(jax.random.key(1), (600, *hw))
    target, _, tokens = tiny_ip2p.draw_batch(d, jax.random.key(2), cfg, 1.0, noise)
    row = np.asarray(target)[:, 0, 0, 0].astype(int) - 100
    k = np.asarray(tiny_ip2p.outcome_of_noise(noise, jnp.full(len(noise), 3)))
    divergent = row < 6
    np.testing.assert_array_equal(outcome[row[divergent]], k[divergent])
    assert (outcome[row[~divergent]] == 0).all() and (~divergent).sum() > 200
    assert np.asarray(tokens)[divergent, 0].tolist() == [1] * divergent.sum()
    assert 0.25 < np.mean(outcome[row[divergent]] == 0) < 0.42  # each outcome about 1/3
    assert set(view[row[divergent]]) == {0, 1}  # the view is still drawn, not the noise's
    free = dataclasses.replace(cfg, outcome_from_noise=False)
    target, _, _ = tiny_ip2p.draw_batch(d, jax.random.key(2), free, 1.0, noise)
    row_free = np.asarray(target)[:, 0, 0, 0].astype(int) - 100
    assert np.mean(outcome[row_free[row_free < 6]] == k[row_free < 6]) < 0.45


def test_balanced_outcomes_draw_instructions_in_proportion_to_their_outcomes():
    """balance_outcomes: an instruction of 3 outcomes is drawn 3 times as often as one of a
    single outcome (3/4 against 1/4 here), each of its outcomes as often as that one;
    off, each instruction half the time."""
    hw = (2, 2, 4)
    # instruction 0: rows 0-2, the three outcomes of view 0; instruction 1: row 3, one outcome
    d = tiny_ip2p.UNetData(
        target_mean=jnp.asarray(np.stack([np.full(hw, 100.0 + r, np.float32)
                                          for r in range(4)])),
        target_std=jnp.zeros((4, *hw)), input_mean=jnp.zeros((1, 2, *hw)),
        input_std=jnp.zeros((1, *hw)), rows=jnp.asarray([[0, 1, 2], [3, 3, 3]]),
        counts=jnp.asarray([3, 1], jnp.int32), active=jnp.asarray([0, 1], jnp.int32),
        views=jnp.zeros(1, jnp.int32), tokens=jnp.asarray([[1, 2], [3, 4], [0, 0]]),
        target_view=jnp.zeros(4, jnp.int32), siblings=jnp.asarray([[0, 1, 2]] * 3 + [[3] * 3]),
        outcomes=jnp.asarray([3, 3, 3, 1], jnp.int32))
    cfg = dataclasses.replace(tiny_ip2p.EditorTrainConfig.smoke(), batch=8000, drop=0.0,
                              identity_share=0.0, degrade=0.0, balance_outcomes=True)
    for balanced, share in ((True, 0.75), (False, 0.5)):
        target, _, tokens = tiny_ip2p.draw_batch(
            d, jax.random.key(3), dataclasses.replace(cfg, balance_outcomes=balanced), 1.0)
        row = np.asarray(target)[:, 0, 0, 0].astype(int) - 100
        np.testing.assert_allclose(np.bincount(row, minlength=4)[:3] / len(row),
                                   share / 3, atol=0.015)
        np.testing.assert_array_equal(np.asarray(tokens)[:, 0] == 1, row < 3)


def test_a_checkpoint_from_before_a_setting_existed_resumes_as_its_default(tmp_path):
    """A UNet checkpoint written before ``outcome_from_noise`` existed resumes a run that
    leaves it off (its default then) and is refused by one that turns it on."""
    from jaxedit.io.checkpoint import save_pytree
    from jaxedit_lab.train_editor import _config_record, read_stage_checkpoint

    cfg = tiny_ip2p.EditorTrainConfig.smoke()
    older = {k: v for k, v in _config_record(cfg).items() if k != "outcome_from_noise"}
    path = tmp_path / "unet.npz"
    state = collections.namedtuple("State", "step")(jnp.asarray(2))  # stored as ".step"
    save_pytree(path, state, kind="editor-unet",
                meta={"config": older, "step": 2, "losses": [1.0, 0.5]})
    assert read_stage_checkpoint(path, "editor-unet", cfg)[1:] == (2, [1.0, 0.5])
    with pytest.raises(DataError, match="other settings"):
        read_stage_checkpoint(path, "editor-unet",
                              dataclasses.replace(cfg, outcome_from_noise=True))


def test_novel_cameras_are_off_the_training_orbit():
    """The quality benchmark's novel cameras: every outcome made for them, all held out, and
    each farther from its nearest training frame than any held-out camera of the orbit."""
    data = edit_data.build_dataset(32, 20, ("ball",))
    novel = edit_data.novel_dataset(32, 3, ("person", "ball"))
    assert novel.scenes == ("ball",) and novel.held_out.all() and len(novel.inputs) == 3
    assert len(novel.targets) == 3 * sum(len(i.outcomes) for i in edit_data.INSTRUCTIONS
                                         if i.applies_to("ball"))
    held = np.flatnonzero(data.held_out)
    on_orbit = edit_data.nearest_training_psnr(data, held, data)
    off = edit_data.nearest_training_psnr(novel, range(3), data)
    assert max(off) < min(on_orbit)


def test_a_scene_s_bands_are_its_orbit_s_from_every_camera():
    """An outcome recolours a surface by its colour, so the novel and the nearer cameras
    take the bands of the scene's training orbit, not terciles of their own views (on the
    ball seen from above those are far off: 0.29 / 0.37 against the orbit's 0.17 / 0.28
    at 64 px)."""
    from jaxedit.scenes import get_scene

    ball = get_scene("ball")
    orbit = edit_data.procedural_views("ball", 32, 20, ball)
    novel = edit_data.novel_views("ball", 32, 3, ball, orbit_views=20)
    near = edit_data.off_orbit_views("ball", 32, 4, ball, orbit.bands)
    assert novel.bands == near.bands == orbit.bands
    assert abs(edit_data.luma_bands(novel.rgba)[0] - orbit.bands[0]) > 0.03  # why it matters
    # the targets follow: a splash outcome of a novel view is made with the orbit's bands
    rgb, pairs = edit_data.scene_pairs(novel, ball)
    splash = edit_data.INSTRUCTIONS.index(edit_data.instruction("splash some colour on it"))
    red = next(t for i, k, t in pairs if i == splash and k == 0)
    np.testing.assert_array_equal(red, edit_data.apply_image_outcome(
        "splash some colour on it", "red shadows", novel.rgba[..., :3], novel.rgba[..., 3],
        orbit.bands))


def test_nearer_training_cameras_are_trained_on_and_stay_off_the_novel_ones():
    """``off_orbit_views``: after a scene's orbit, that many nearer cameras (the object larger
    in the frame, seen from up to above the orbit's band), none held out, every outcome made
    for them; the person has none; the novel cameras stay farther from every training frame
    than the orbit's held-out ones are, and ``dataset.npz`` records the count."""
    from jaxedit_lab.train_editor import _dataset_record

    plain = edit_data.build_dataset(32, 20, ("person", "ball"))
    data = edit_data.build_dataset(32, 20, ("person", "ball"), off_orbit_views_per_scene=5)
    ball = data.scenes.index("ball")
    assert len(data.inputs) == len(plain.inputs) + 5
    assert data.held_out.sum() == plain.held_out.sum()
    np.testing.assert_array_equal(data.inputs[: len(plain.inputs)], plain.inputs)
    extra = np.arange(len(plain.inputs), len(data.inputs))
    assert (data.scene[extra] == ball).all() and not data.held_out[extra].any()
    per_view = sum(len(i.outcomes) for i in edit_data.INSTRUCTIONS if i.applies_to("ball"))
    assert all((data.target_view == v).sum() == per_view for v in extra)
    covered = (data.inputs[data.scene == ball] < 250).any(-1).mean(axis=(1, 2))
    assert covered[20:].mean() > 1.5 * covered[:20].mean()  # nearer: the ball is larger
    novel = edit_data.novel_dataset(32, 3, ("ball",), orbit_views=20)
    held = np.flatnonzero(data.held_out & (data.scene == ball))
    assert (max(edit_data.nearest_training_psnr(novel, range(3), data))
            < min(edit_data.nearest_training_psnr(data, held, data)))
    cfg = dataclasses.replace(tiny_ip2p.EditorTrainConfig.smoke(), off_orbit_views=5)
    assert _dataset_record(cfg)["off_orbit_views"] == 5
    with pytest.raises(DataError, match="--off-orbit-views"):
        dataclasses.replace(cfg, off_orbit_views=-1).check()


def test_identity_only_nearer_cameras_are_inputs_without_edit_targets():
    """``--off-orbit-identity-only``: the nearer cameras are the same training inputs, but no
    edit target points at them (they are drawn as identity examples only), the orbit's
    targets are unchanged, and the dataset record says so; asked for without nearer
    cameras, it is refused naming the flag."""
    from jaxedit_lab.train_editor import _dataset_record

    edited = edit_data.build_dataset(32, 20, ("ball",), off_orbit_views_per_scene=4)
    kept = edit_data.build_dataset(32, 20, ("ball",), off_orbit_views_per_scene=4,
                                   off_orbit_edits=False)
    np.testing.assert_array_equal(kept.inputs, edited.inputs)
    np.testing.assert_array_equal(kept.held_out, edited.held_out)
    assert not kept.held_out[20:].any()
    assert kept.target_view.max() < 20 <= edited.target_view.max()
    orbit = edited.target_view < 20
    np.testing.assert_array_equal(kept.targets, edited.targets[orbit])
    np.testing.assert_array_equal(kept.target_view, edited.target_view[orbit])
    cfg = dataclasses.replace(tiny_ip2p.EditorTrainConfig.smoke(), off_orbit_views=4,
                              off_orbit_edits=False).check()
    assert _dataset_record(cfg)["off_orbit_edits"] is False
    with pytest.raises(DataError, match="--off-orbit-identity-only.*--off-orbit-views"):
        dataclasses.replace(cfg, off_orbit_views=0).check()


def test_geometry_only_nearer_cameras_get_the_geometry_targets_alone():
    """``--off-orbit-geometry-only``: the nearer cameras get the bigger ball's targets (the
    same images as with every edit made for them) and no image-space edit's, the orbit keeps
    every instruction's targets, the record says so, and the flag is refused naming itself
    beside ``--off-orbit-identity-only`` or without nearer cameras."""
    from jaxedit_lab.train_editor import _dataset_record

    edited = edit_data.build_dataset(32, 20, ("ball",), off_orbit_views_per_scene=4)
    shaped = edit_data.build_dataset(32, 20, ("ball",), off_orbit_views_per_scene=4,
                                     off_orbit_geometry_only=True)
    np.testing.assert_array_equal(shaped.inputs, edited.inputs)
    geometry = [i for i, ins in enumerate(edit_data.INSTRUCTIONS) if ins.kind == "geometry"]
    near = shaped.target_view >= 20
    assert near.sum() == 4 and np.isin(shaped.target_instruction[near], geometry).all()
    wanted = (edited.target_view < 20) | np.isin(edited.target_instruction, geometry)
    np.testing.assert_array_equal(shaped.targets, edited.targets[wanted])
    np.testing.assert_array_equal(shaped.target_view, edited.target_view[wanted])
    cfg = dataclasses.replace(tiny_ip2p.EditorTrainConfig.smoke(), off_orbit_views=4,
                              off_orbit_geometry_only=True).check()
    assert _dataset_record(cfg)["off_orbit_geometry_only"] is True
    for bad in (dict(off_orbit_views=0), dict(off_orbit_edits=False)):
        with pytest.raises(DataError, match="--off-orbit-geometry-only"):
            dataclasses.replace(cfg, **bad).check()


def test_a_folder_s_training_dataset_is_rebuilt_from_its_record(tmp_path):
    """The benchmarks rebuild the dataset an editor folder was trained on from the record in
    its instructions.json: the same arrays as the run built; a record from before a setting
    existed reads as such a run had it; a folder with no record is refused naming the file."""
    from jaxedit_lab.train_editor import rebuild_dataset, trained_on

    def listing(record):
        folder = tmp_path / str(len(list(tmp_path.iterdir())))
        folder.mkdir()
        (folder / "instructions.json").write_text(json.dumps(
            {"instructions": [], **({"dataset": record} if record is not None else {})}))
        return folder

    record = {"size": 32, "procedural_views": 20, "scenes": ["ball"], "off_orbit_views": 4,
              "off_orbit_edits": False, "holdout_every": edit_data.HOLDOUT_EVERY}
    rebuilt = rebuild_dataset(trained_on(listing(record)))
    built = edit_data.build_dataset(32, 20, ("ball",), off_orbit_views_per_scene=4,
                                    off_orbit_edits=False)
    for name, array in built.arrays().items():
        np.testing.assert_array_equal(getattr(rebuilt, name), array, err_msg=name)
    older = {k: v for k, v in record.items() if not k.startswith("off_orbit")}
    assert trained_on(listing(older)) == {**older, "off_orbit_views": 0,
                                          "off_orbit_edits": True,
                                          "off_orbit_geometry_only": False}
    with pytest.raises(DataError, match="instructions.json.*lists no training dataset"):
        trained_on(listing(None))
    for damaged in ([], {**record, "size": "64"}, {k: v for k, v in record.items()
                                                   if k != "scenes"}):
        with pytest.raises(DataError, match="instructions.json.*record is not"):
            trained_on(listing(damaged))


def test_train_editor_refuses_an_unknown_scene_before_any_work(tmp_path, capfd):
    code, err = _main(["train-editor", "--scenes", "person,moon", "--out", tmp_path / "r"],
                      capfd)
    assert code == 2 and err.err.count("\n") == 1
    assert "--scenes" in err.err and "moon" in err.err
    assert not (tmp_path / "r" / "checkpoints").exists()


# ----------------------------------------------------------------------------- the bundled model

def test_the_bundled_editor_is_small_complete_and_edits():
    folder = bundled_editor()
    size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    assert size <= 20 * 2 ** 20
    assert native_size(folder) == 64
    assert len(instructions(folder)) == len(edit_data.INSTRUCTIONS)
    assert (folder / "README.md").is_file()


def test_diffusers_pipeline_gives_the_jax_editors_edit():
    """StableDiffusionInstructPix2PixPipeline.from_pretrained on the bundled folder, run from
    the JAX editor's noised latent over the JAX editor's timesteps, gives its edit."""
    torch = pytest.importorskip("torch")
    diffusers = pytest.importorskip("diffusers")
    from jaxedit.editors import jax_ip2p as jx
    from jaxedit.editors.diffusion import timestep_schedule

    folder = bundled_editor()
    steps, t_start = 4, 800
    editor = JaxIP2PEditor.from_pretrained(folder, size=64, steps=steps)
    data = edit_data.person_views(64)
    view = edit_data.composite(data.rgba[5])[None]
    prompt = "splash some colour on it"
    rng = np.random.default_rng(0)
    vae_noise = rng.standard_normal((1, 16, 16, 4)).astype(np.float32)
    sde_noise = rng.standard_normal((1, 16, 16, 4)).astype(np.float32)
    cfg = editor.config()
    # jitted: run eagerly, the VAE and the steps around the scan compiled ~200 primitives
    ours = np.asarray(jx.edit_with_noise_jit(
        editor.nets, jnp.asarray(view), jnp.asarray(view), jnp.asarray(editor.encode(prompt)),
        jnp.asarray(editor.encode("")), jnp.asarray([t_start], jnp.int32),
        jnp.asarray(vae_noise), jnp.asarray(sde_noise), editor.schedule, cfg))
    latents, _ = eqx.filter_jit(jx.encode_latents)(editor.nets.vae, jnp.asarray(view),
                                                   jnp.asarray(view), jnp.asarray(vae_noise), cfg)
    a = float(editor.schedule.alphas_cumprod[t_start])
    x_t = (np.sqrt(a) * np.asarray(latents) + np.sqrt(1 - a) * sde_noise).astype(np.float32)

    pipe = diffusers.StableDiffusionInstructPix2PixPipeline.from_pretrained(
        folder, safety_checker=None, requires_safety_checker=False)
    scheduler = pipe.scheduler
    ours_ts = timestep_schedule(t_start, steps)
    original = scheduler.set_timesteps

    def set_ours(n, device=None):  # the pipeline's loop over the JAX editor's timesteps
        original(n, device=device)
        scheduler.timesteps = torch.tensor(ours_ts, dtype=torch.long)
    scheduler.set_timesteps = set_ours
    # DDIM steps from t to t - N // n: n = N / spacing makes that the next of ours_ts.
    n = scheduler.config.num_train_timesteps // (ours_ts[0] - ours_ts[1])
    image = torch.from_numpy(view.transpose(0, 3, 1, 2))  # [0, 1]: the pipeline normalises
    text, image_scale = editor.guidance  # the folder's (2, 1.5): the JAX edit's default
    theirs = pipe(prompt, image=image, num_inference_steps=n, guidance_scale=text,
                  image_guidance_scale=image_scale, latents=torch.from_numpy(x_t.transpose(0, 3, 1, 2)),
                  output_type="np").images
    np.testing.assert_allclose(theirs, ours, atol=2e-4)


def test_identity_per_scene_averages_each_scene_s_views_alone():
    """The quality benchmark's per-scene figures: each scene's is the mean over its own views
    only (identity at each T, the VAE round trip, an instruction's edits over its draws), so
    the views' counts weight them back to the pooled figure."""
    from types import SimpleNamespace

    from jaxedit_lab.train_editor.quality import _identity_per_scene, _scene_means, psnr

    rng = np.random.default_rng(0)
    data = SimpleNamespace(scenes=("face", "ball"), scene=np.array([0, 1, 1, 0, 1]))
    views = [4, 0, 2]  # ball, face, ball
    inputs = rng.uniform(size=(3, 4, 4, 3)).astype(np.float32)
    near, far = inputs + 0.01, inputs + rng.normal(0, 0.1, inputs.shape).astype(np.float32)
    out = _identity_per_scene(data, views, inputs, {0.45: near, 0.98: far}, far)
    assert set(out) == {"face", "ball"}
    np.testing.assert_allclose(out["face"]["identity_psnr_db"]["0.98"],
                               psnr(far[1:2], inputs[1:2])[0], rtol=1e-6)
    np.testing.assert_allclose(out["ball"]["vae_roundtrip_psnr_db"],
                               np.mean(psnr(far[[0, 2]], inputs[[0, 2]])), rtol=1e-6)
    np.testing.assert_allclose(out["ball"]["identity_psnr_db"]["0.45"], 40.0, rtol=1e-4)
    # An instruction's edits per scene: one value per draw, a view repeated for each.
    rows = [4, 4, 0, 0, 2, 2]
    by = _scene_means(data, rows, np.array([1.0, 3.0, 10.0, 20.0, 5.0, 7.0]))
    assert by == {"face": 15.0, "ball": 4.0}
