"""Flags generated from the config trees (experiments/flags.py): defaults, help, errors.

The oracle is the dataclasses themselves: every generated flag's parsed default must be
its field's default, its help the field's docstring entry, and a library error that
names the field must reach the user as the flag.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools

import pytest

from experiments import cli, flags
from jaxedit import DataError


def _generated():
    """(command, FlagSet, Flag) of every command with generated flags."""
    out = []
    for name in cli.COMMANDS:
        module = cli._module(name)
        for flag_set in getattr(module, "FLAGS", ()):
            out += [(name, flag_set, f) for f in flag_set.flags]
    return out


GENERATED = _generated()


def _parse(command: str, *argv: str) -> argparse.Namespace:
    required = {"reconstruct": ["--data", "unchecked"], "make-scene": ["face"],
                "process-data": ["--images", "unchecked"], "report": ["unchecked"],
                "view": ["unchecked"], "render": ["--scene", "unchecked"],
                "clip-metrics": ["--run", "r", "--caption-orig", "a", "--caption-edit", "b"],
                }.get(command, [])
    return cli.parse([command, *required, *argv])


def test_the_commands_with_settings_generate_their_flags():
    commands = {c for c, _, _ in GENERATED}
    assert {"reconstruct", "edit", "ablation", "process-data", "demo", "make-scene",
            "bench"} <= commands


@pytest.mark.parametrize("command, flag_set, flag", GENERATED,
                         ids=[f"{c}{f.flag}" for c, _, f in GENERATED])
def test_every_cli_default_is_its_fields_default(command, flag_set, flag):
    if flag.required:
        pytest.skip("a required flag has no default")
    args = _parse(command)
    tree_default = functools.reduce(getattr, flag.field.split("."), flag_set.root())
    assert getattr(args, flag.dest) == tree_default
    assert flag_set.default(flag) == tree_default


@pytest.mark.parametrize("command, flag_set, flag", GENERATED,
                         ids=[f"{c}{f.flag}" for c, _, f in GENERATED])
def test_help_is_the_fields_docstring(command, flag_set, flag):
    cls, field, _ = flag_set.owner(flag)
    action = next(a for a in cli.command_parser(command).arguments if flag.flag in a.option_strings)
    doc = flags.attribute_docs(cls)[field.name]
    assert action.help.startswith(doc.replace("%", "%%"))


@pytest.mark.parametrize("command", sorted({c for c, _, _ in GENERATED}))
def test_no_flags_build_the_default_tree(command):
    module = cli._module(command)
    args = _parse(command)
    built = module.run_config(args)
    required = {f.field: getattr(args, f.dest) for f in module.FLAGS[0].flags if f.required}
    assert built == flags.with_fields(module.FLAGS[0].root(), required)


def test_reconstruct_tree_from_flags():
    from experiments import reconstruct
    from jaxedit.train import TrainConfig

    args = _parse("reconstruct", "--iters", "7", "--densify-until", "5", "--camera-lr", "1e-4",
                  "--background", "black", "--log-every", "3")
    config = reconstruct.run_config(args)
    assert (config.train.iterations, config.train.densify.stop_at, config.log_every) == (7, 5, 3)
    assert config.train.background == "black"
    # --camera-lr keeps TrainConfig's decay ratio (1e-3 -> 1e-5)
    assert config.train.lr_camera_final == pytest.approx(1e-4 * TrainConfig.lr_camera_final
                                                         / TrainConfig.lr_camera)
    rest = dataclasses.replace(config.train, iterations=TrainConfig.iterations,
                               densify=TrainConfig().densify, background="white",
                               lr_camera=TrainConfig.lr_camera,
                               lr_camera_final=TrainConfig.lr_camera_final)
    assert rest == TrainConfig()


def test_edit_mode_defaults_yield_only_to_given_flags(tmp_path):
    from experiments import edit
    from jaxedit.edit.plan import ProEditConfig

    in2n = edit.run_config(_parse("edit", "--mode", "in2n"))
    assert in2n.plan == ProEditConfig.for_mode("in2n")  # IN2N's warm-up 0, not the flag's 30
    given = edit.run_config(_parse("edit", "--mode", "in2n", "--warmup", "30", "--async"))
    assert given.plan == ProEditConfig.for_mode("in2n", warmup=30, asynchronous=True)
    # a config file's values count as given too
    (tmp_path / "c.json").write_text('{"warmup": 30, "asynchronous": true}')
    from_file = edit.run_config(_parse("edit", "--mode", "in2n", "--config",
                                       str(tmp_path / "c.json")))
    assert from_file.plan.warmup == 30 and from_file.plan.asynchronous
    capped = edit.run_config(_parse("edit", "--max-gaussians", "5000"))
    assert capped.train.densify.max_gaussians == 5000


@pytest.mark.parametrize("command, field, flag", [
    ("edit", "max_seconds", "--max-subtask-seconds"), ("edit", "max_gaussians", "--max-gaussians"),
    ("edit", "threshold", "--threshold"), ("edit", "run_dir", "--out"),
    ("edit", "select", "--select"), ("reconstruct", "iterations", "--iters"),
    ("reconstruct", "stop_at", "--densify-until"), ("reconstruct", "lr_camera", "--camera-lr"),
    ("reconstruct", "sh_degree", "--sh-degree"),
])
def test_errors_that_name_fields_print_flags(command, field, flag):
    args = _parse(command)
    line = str(cli.named_by_flag(DataError(field, "is wrong"), args))
    assert line == f"{flag}: is wrong"
    # a path or an unknown name is left alone
    assert str(cli.named_by_flag(DataError("/some/file.ply", "x"), args)) == "/some/file.ply: x"


def test_errors_about_a_given_path_say_which_flag(tmp_path):
    args = _parse("edit", "--ip2p-weights", str(tmp_path / "nowhere"))
    error = DataError(tmp_path / "nowhere", "InstructPix2Pix folder not found")
    assert str(cli.named_by_flag(error, args)).endswith("not found (given as --ip2p-weights)")


@pytest.mark.parametrize("argv, needle", [
    (["edit", "--max-subtask-seconds", "-1"], "--max-subtask-seconds: must be > 0"),
    (["edit", "--warmup", "-1"], "--warmup: must be >= 0"),
    (["edit", "--max-gaussians", "0"], "--max-gaussians: must be >= 1"),
    (["edit", "--guidance", "2", "0"], "--guidance: need text >= 0 and image > 0"),
    (["reconstruct", "--cull-alpha", "1.5"], "--cull-alpha: must be in (0, 1)"),
    (["reconstruct", "--sh-degree", "4"], "--sh-degree: must be in [0, 3]"),
    (["reconstruct", "--iters", "0"], "--iters: must be >= 1"),
])
def test_range_errors_name_the_flag(argv, needle):
    command = cli._module(argv[0])
    args = _parse(*argv)
    with pytest.raises(DataError) as e:
        command.run_config(args)
    assert str(cli.named_by_flag(e.value, args)).startswith(needle)


def test_attribute_docs_reads_grouped_and_continued_entries():
    @dataclasses.dataclass(frozen=True)
    class Knobs:
        """Knobs.

        Attributes:
          a, b: shared text
            continued here.
          c: ``c``'s text, see :func:`jaxedit.train.fit`.
        """

        a: int = 1
        b: int = 2
        c: float = 0.5

    docs = flags.attribute_docs(Knobs)
    assert docs == {"a": "shared text continued here.", "b": "shared text continued here.",
                    "c": "c's text, see jaxedit.train.fit."}


def test_a_comma_list_field_from_the_command_line_and_from_config_json(tmp_path):
    """A tuple[str, ...] field is a comma-separated flag; config.json records it as a list,
    which --config reads back to the same tuple."""
    import json

    from experiments import ablation

    args = _parse("ablation", "--prompts", "make his head bigger, give him a marble texture")
    assert ablation.run_config(args).prompts == ("make his head bigger",
                                                 "give him a marble texture")
    path = tmp_path / "config.json"
    path.write_text(json.dumps({"prompts": ["make his head bigger"], "variants": ["3", "3:0"]}))
    config = ablation.run_config(cli.parse(["ablation", "--config", str(path)]))
    assert (config.prompts, config.variants) == (("make his head bigger",), ("3", "3:0"))
    path.write_text(json.dumps({"prompts": [1, 2]}))
    with pytest.raises(DataError, match="prompts"):
        cli.parse(["ablation", "--config", str(path)])


def test_a_config_file_changes_no_shared_parser(tmp_path):
    """--config's values are the defaults of a parser built for that parse: the process's
    parser (which check_paths and the demo read) keeps its defaults and required flags."""
    path = tmp_path / "c.json"
    path.write_text('{"scene": "elsewhere.ply", "size": 48}')
    shared = cli.command_parser("render")
    before = [(a.dest, a.default, a.required) for a in shared.arguments]
    args = cli.parse(["render", "--config", str(path), "--size", "32"])
    assert (str(args.scene), args.size, args.command) == ("elsewhere.ply", 32, "render")
    assert args._module is cli._module("render") and {"scene", "size"} <= getattr(args, flags.GIVEN)
    assert [(a.dest, a.default, a.required) for a in shared.arguments] == before
    with pytest.raises(SystemExit):  # without the file, --scene is required again
        cli.parse(["render", "--size", "32"])


def test_the_ddim_step_default_is_read_from_one_place():
    """Every DDIM step count default (both editors, the edit command, the ablation) is
    jaxedit.editors.diffusion.DDIM_STEPS."""
    import inspect

    from jaxedit.editors import jax_ip2p
    from jaxedit.editors.diffusion import DDIM_STEPS
    from jaxedit_lab.ablation import AblationConfig

    defaults = [jax_ip2p.SamplerConfig.steps, AblationConfig.ip2p_steps,
                _parse("edit").ip2p_steps]
    fns = [jax_ip2p.JaxIP2PEditor.__init__, jax_ip2p.JaxIP2PEditor.from_pretrained,
           jax_ip2p.JaxIP2PEditor.bundled]
    try:  # the torch reference, where its extra is installed
        from jaxedit.editors import ip2p

        fns += [ip2p.InstructPix2PixEditor.__init__, ip2p.InstructPix2PixEditor.from_pretrained]
    except ImportError:
        pass
    defaults += [inspect.signature(fn).parameters["steps"].default for fn in fns]
    assert defaults == [DDIM_STEPS] * len(defaults)


def test_edit_guidance_flag_and_config_value(tmp_path):
    from experiments import edit

    assert edit.run_config(_parse("edit")).plan.guidance is None    # the editor's own
    assert edit.run_config(_parse("edit", "--guidance", "2", "1.5")).plan.guidance == (2.0, 1.5)
    (tmp_path / "c.json").write_text('{"guidance": [3, 1.25]}')
    assert edit.run_config(_parse("edit", "--config", str(tmp_path / "c.json"))
                           ).plan.guidance == (3.0, 1.25)


def _flag_sets():
    return [(name, s) for name in cli.COMMANDS for s in getattr(cli._module(name), "FLAGS", ())]


@pytest.mark.parametrize("command, flag_set", _flag_sets(),
                         ids=[f"{c}:{s.root.__name__}" for c, s in _flag_sets()])
def test_every_setting_of_every_command_has_a_route_and_its_own_help(command, flag_set):
    """Each field of the tree a command builds is a flag (and so a --config key), or is set
    from another of the command's flags (``derived``); no two flags share a help line."""
    routed = {f.field for f in flag_set.flags} | set(flag_set.derived)
    assert set(flags.leaf_fields(flag_set.root)) - routed == set()
    helps = [flags.attribute_docs(flag_set.owner(f)[0])[flag_set.owner(f)[1].name]
             for f in flag_set.flags]
    shared = {h for h in helps if helps.count(h) > 1}
    assert not shared, shared


def test_a_nested_setting_from_the_command_line_and_from_nested_config_keys(tmp_path):
    from experiments import edit, reconstruct

    args = _parse("reconstruct", "--train.densify.grad-threshold", "1e-4")
    assert reconstruct.FLAGS[0].build(args).train.densify.grad_threshold == 1e-4
    table = tmp_path / "c.toml"
    table.write_text("[train.densify]\ngrad_threshold = 3e-4\nmax_gaussians = 5000\n"
                     "refine_from_warmup = true\n")
    built = reconstruct.FLAGS[0].build(_parse("reconstruct", "--config", str(table)))
    assert (built.train.densify.grad_threshold, built.train.densify.max_gaussians,
            built.train.densify.refine_from_warmup) == (3e-4, 5000, True)
    dotted = tmp_path / "c.json"
    dotted.write_text('{"train.densify.grad_threshold": 5e-4, "plan.loss_window": 7}')
    tree = edit.run_config(cli.parse(["edit", "--config", str(dotted)]))
    assert (tree.train.densify.grad_threshold, tree.plan.loss_window) == (5e-4, 7)
    bad = tmp_path / "bad.toml"
    bad.write_text("[train.densify]\nno_such_setting = 1\n")
    with pytest.raises(DataError, match="train.densify.no_such_setting"):
        _parse("reconstruct", "--config", str(bad))
