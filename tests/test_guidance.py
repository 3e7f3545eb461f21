"""An editor's guidance: the scales its folder recommends are every edit's default (issue 51).

The bundled model is trained so that the empty prompt keeps the view; its text guidance then
scales a whole edit, and it edits with gain 1 at text 2 (7.5 overshoots 1.9x). Its folder says
so (``instructions.json``'s ``"guidance"``), and every edit that names no guidance uses it: the
editors' own calls, :func:`edit_views`, the difficulty, the run (which records what it used).
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from jaxedit.edit import DifficultyOracle
from jaxedit.edit.plan import ProEditConfig
from jaxedit.editors import BUNDLED, edit_views, editor_guidance, recommended_guidance
from jaxedit_lab.simulated import SimulatedEditor
from jaxedit.editors.diffusion import IP2P_GUIDANCE, check_guidance
from jaxedit.errors import DataError


def _folder(tmp_path, table) -> object:
    folder = tmp_path / "model"
    folder.mkdir()
    if table is not None:
        (folder / "instructions.json").write_text(
            table if isinstance(table, str) else json.dumps(table))
    return folder


@pytest.mark.parametrize("table, want", [
    (None, IP2P_GUIDANCE),                                   # no instructions.json
    ({"instructions": []}, IP2P_GUIDANCE),                   # a list without guidance
    ({"instructions": [], "guidance": [2, 1.5]}, (2.0, 1.5)),
    ({"instructions": [], "guidance": [0, 4]}, (0.0, 4.0)),  # no text guidance is legal
])
def test_a_folder_recommends_its_guidance_or_gets_ip2ps(tmp_path, table, want):
    assert recommended_guidance(_folder(tmp_path, table)) == want


@pytest.mark.parametrize("table, needle", [
    ({"instructions": [], "guidance": [2]}, "need two scales"),
    ({"instructions": [], "guidance": "2,1.5x"}, "need two scales"),
    ({"instructions": [], "guidance": [2, 0]}, "image > 0"),
    ({"instructions": [], "guidance": [-1, 1.5]}, "text >= 0"),
    ({"instructions": [], "guidance": [2, float("nan")]}, "text >= 0 and image > 0"),
    ("{not json", "unreadable"),
])
def test_a_bad_recommendation_names_the_file(tmp_path, table, needle):
    folder = _folder(tmp_path, table)
    with pytest.raises(DataError, match=needle) as e:
        recommended_guidance(folder)
    assert str(folder / "instructions.json") in str(e.value)


def test_the_bundled_editor_recommends_text_2():
    assert recommended_guidance(BUNDLED) == recommended_guidance() == (2.0, 1.5)


def test_the_jax_editor_takes_its_folders_guidance_and_records_it(tmp_path):
    from jaxedit.editors.jax_ip2p import JaxIP2PEditor

    editor = JaxIP2PEditor.from_pretrained(BUNDLED, steps=1)
    assert editor.guidance == (2.0, 1.5)
    assert editor.describe()["guidance"] == [2.0, 1.5]
    assert editor.config().guidance == (2.0, 1.5)                # an edit naming none
    assert editor.config((7.5, 1.5)).guidance == (7.5, 1.5)      # an edit naming its own
    with pytest.raises(DataError, match="guidance"):
        JaxIP2PEditor(editor.nets.unet, editor.nets.vae, editor.text_encoder, editor.tokenize,
                      editor.schedule, guidance=(2.0, -1.0))


class RecordingEditor(SimulatedEditor):
    """The simulated editor with a recommendation of its own, recording each call's scales."""

    guidance = (3.0, 1.25)

    def __init__(self):
        super().__init__()
        self.seen = []

    def edit(self, *args, guidance=None, **kwargs):
        self.seen.append(guidance)
        return super().edit(*args, guidance=guidance, **kwargs)


def test_editor_guidance_prefers_the_callers_then_the_editors_then_ip2ps():
    assert editor_guidance(RecordingEditor()) == (3.0, 1.25)
    assert editor_guidance(RecordingEditor(), (5, 2)) == (5.0, 2.0)
    assert editor_guidance(object()) == IP2P_GUIDANCE             # an editor without one
    with pytest.raises(DataError, match="guidance"):
        editor_guidance(RecordingEditor(), (5, 0))


def test_edit_views_and_the_difficulty_pass_the_editors_own_scales():
    editor = RecordingEditor()
    views = np.full((2, 8, 8, 3), 0.5, np.float32)
    keys = list(jax.random.split(jax.random.key(0), 2))
    edit_views(editor, views, views, editor.encode(""), keys)
    edit_views(editor, views, views, editor.encode(""), keys, guidance=(5.0, 2.0))
    assert editor.seen == [(3.0, 1.25)] * 2 + [(5.0, 2.0)] * 2
    oracle = DifficultyOracle(editor, views, editor.instructions[0])
    assert oracle.guidance == (3.0, 1.25)
    assert DifficultyOracle(editor, views, editor.instructions[0],
                            guidance=(4, 1.5)).guidance == (4.0, 1.5)


def test_the_simulated_editors_default_is_ip2ps_bit_for_bit():
    editor = SimulatedEditor()
    image = np.random.default_rng(0).uniform(size=(12, 12, 3)).astype(np.float32)
    e = editor.encode(editor.instructions[0])
    key = jax.random.key(3)
    np.testing.assert_array_equal(editor.edit(image, image, e, key),
                                  editor.edit(image, image, e, key, guidance=(7.5, 1.5)))
    assert not np.array_equal(editor.edit(image, image, e, key),
                              editor.edit(image, image, e, key, guidance=(2.0, 1.5)))


def test_the_plans_guidance_is_the_editors_unless_given():
    assert ProEditConfig().guidance is None
    assert ProEditConfig(guidance=[2, 1.5]).guidance == (2.0, 1.5)   # a JSON list, normalised
    with pytest.raises(DataError, match="guidance"):
        ProEditConfig(guidance=(2.0, 0.0))


def test_check_guidance_reads_two_finite_scales():
    assert check_guidance((7.5, 1.5)) == (7.5, 1.5)
    for bad in ((1.0,), (1.0, 2.0, 3.0), ("a", 1), None, (float("inf"), 1.5)):
        with pytest.raises(DataError):
            check_guidance(bad)


def test_bundle_editor_records_the_guidance_it_is_given(tmp_path, monkeypatch, capsys):
    import importlib.util
    import shutil
    from pathlib import Path

    import jaxedit.editors

    spec = importlib.util.spec_from_file_location(
        "bundle_editor", Path(__file__).resolve().parents[1] / "scripts" / "bundle_editor.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    source = tmp_path / "trained"
    shutil.copytree(BUNDLED, source)
    table = json.loads((source / "instructions.json").read_text())
    (source / "instructions.json").write_text(json.dumps({"instructions": table["instructions"]}))
    target = tmp_path / "package" / "tiny-ip2p"
    monkeypatch.setattr(jaxedit.editors, "BUNDLED", target)   # not the installed copy
    assert recommended_guidance(source) == IP2P_GUIDANCE
    assert script.main([str(source), "--guidance", "3,1.25"]) == 0
    assert recommended_guidance(target) == (3.0, 1.25)
    assert json.loads((target / "instructions.json").read_text())["instructions"] == \
        table["instructions"]
    assert "guidance (3.0, 1.25)" in capsys.readouterr().out
    with pytest.raises(SystemExit):   # argparse's one line and status 2
        script.main([str(source), "--guidance", "3"])
    assert "want TEXT,IMAGE" in capsys.readouterr().err
