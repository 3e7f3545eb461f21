"""The method presets: what ``edit --preset NAME --print-config`` prints is what the run uses.

The oracle is the trainer the run builds (:func:`jaxedit.edit.progressive.make_trainer`, as
:func:`jaxedit.pipelines.edit_run.run_edit` calls it) and the editor the command builds: their
settings are compared field by field with the printed tree.
"""

from __future__ import annotations

import dataclasses
import json
import types

import numpy as np
import pytest

from experiments import cli
from experiments import edit as edit_command
from experiments.editors import make_editor
from jaxedit import gaussians as G
from jaxedit import scenes
from jaxedit.edit import progressive
from jaxedit.edit.trainer import EditTrainConfig, default_max_gaussians
from jaxedit.pipelines.presets import PRESETS


@pytest.fixture(scope="module")
def scene():
    """A stand-in of the run's inputs: the training cameras and the input Gaussians."""
    cams, train, _ = scenes.scene_cameras(scenes.get_scene("face"), views=4, test_views=1,
                                          size=16)
    points = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    g = G.from_points(points, np.full((50, 3), 0.5, np.float32), sh_degree=0, capacity=64)
    return types.SimpleNamespace(train_cameras=cams[train]), g


def _printed(capsys, *argv) -> dict:
    assert cli.main(["edit", *argv, "--print-config"]) in (0, None, {})
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("argv", [[p] for p in PRESETS] + [["in2n", "--mode", "proedit"],
                                                            ["proedit", "--mode", "in2n"],
                                                            ["nd", "--warmup", "12"],
                                                            ["nd", "--train.densify.warmup", "4"]],
                         ids=lambda a: "-".join(a))
def test_the_printed_config_is_what_the_run_uses(capsys, scene, argv):
    data, g = scene
    printed = _printed(capsys, "--preset", *argv)
    tree = edit_command.run_config(cli.parse(["edit", "--preset", *argv]))
    trainer = progressive.make_trainer(tree.plan, tree.train, data, g)
    used = dataclasses.asdict(trainer.config.densify)
    shown = printed["train"]["densify"]
    # the two fields the run completes when unset: the cap from the input, the warm-up W
    # from the plan
    assert used.pop("max_gaussians") == (shown.pop("max_gaussians") or
                                         default_max_gaussians(int(g.num_alive())))
    assert used.pop("warmup") == (printed["plan"]["warmup"] if shown.pop("warmup") is None
                                  else tree.train.densify.warmup)
    assert used == shown
    assert "adaptive" not in printed["train"]
    for name in ("lr_means", "lr_sh_dc", "lr_opacity", "sh_degree"):
        assert getattr(trainer.config, name) == printed["train"][name], name
    assert printed["plan"]["mode"] == tree.plan.mode
    assert printed["editor"]["kind"] == "simulated"
    assert type(make_editor(tree.editor)).__name__ == "SimulatedEditor"


def test_in2n_runs_classic_density_control_and_says_so(capsys):
    printed = _printed(capsys, "--preset", "in2n")
    assert printed["train"]["densify"]["budget"] is False
    assert printed["train"]["densify"]["reset_every"] > 0
    assert _printed(capsys, "--preset", "proedit")["train"]["densify"]["budget"] is True
    # a flag given wins over the preset, and the run follows the flag
    tree = edit_command.run_config(cli.parse(["edit", "--preset", "in2n",
                                              "--train.densify.budget"]))
    assert tree.train.densify.budget and tree.train.train_config().densify.budget


def test_the_grad_threshold_flag_reaches_the_strategy_unchanged(scene):
    """The flag's DensifyConfig is the one the training state carries and its strategy reads."""
    data, g = scene
    tree = edit_command.run_config(cli.parse(["edit", "--preset", "in2n",
                                              "--train.densify.grad-threshold", "3e-4"]))
    trainer = progressive.make_trainer(tree.plan, tree.train, data, g)
    state = trainer.init(g)
    assert state.config.densify.grad_threshold == 3e-4
    assert state.strategy is trainer.init(g).strategy  # built once per config


def test_library_modes_default_to_their_presets_trainer():
    for mode in ("proedit", "nd", "in2n"):
        assert EditTrainConfig.for_mode(mode) == PRESETS[mode]().train
    assert EditTrainConfig.for_mode("in2n") == EditTrainConfig().classic()
