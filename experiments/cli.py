"""Subcommand dispatch: the parser of every command, the shared flags, and :func:`main`.

Each subcommand lives in its own module ``experiments/<name>.py`` (dashes become
underscores) and defines::

    HELP: str                                  # one line for --help
    def add_arguments(parser) -> None          # its own flags
    def run(args) -> dict | None               # does the work; returns metrics to print

Shared flags (every subcommand): --out, --seed, --config, --device, --quiet.
``--config FILE`` (JSON or TOML) sets any flag by its dest name; flags given on
the command line win. Every run directory receives ``config.json`` with the
resolved flags and the jaxedit version, so a run can be reproduced from it.
Bad input (:class:`jaxedit.DataError`) and bad flags print one line to stderr and
exit with status 2.

The rest is split by job: :mod:`experiments.configfiles` (``--config`` read and checked
as the command line is, each run's ``config.json``), :mod:`experiments.rundirs` (every path
flag checked before any work, ``--out``'s lock, what a failed run created removed) and
:mod:`experiments.distributed` (``edit`` and ``reconstruct`` as several supervised
processes, ``--coordinator HOST:PORT --num-processes N --process-id I``: only process 0
checks, locks and writes ``--out``). Their names stay importable from here.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import sys
from pathlib import Path

from .configfiles import _config_file, config_values, jsonable, load_config, write_run_config
from .distributed import _failed, _is_worker, _stdout_for_the_result, distributed_config, supervised
from .rundirs import check_paths, claimed_out, write_refused, writes
# finite_float (re-exported), TYPE_READERS: how a flag's type reads its text.
from .flags import (GIVEN, TYPE_READERS, as_flags, finite_float, flag_names)  # noqa: F401
# Names of the split-off modules that callers import from here.
from .configfiles import config_value, convert, flag_label  # noqa: F401
from .distributed import distributed_flags  # noqa: F401
from .rundirs import (KEPT_RECORD, OUTPUT_DIRS, OUTPUT_FILES, WRITE_REFUSED,  # noqa: F401
                      check_input_path, check_output_path, remove_created)

COMMANDS = ["demo", "make-scene", "reconstruct", "edit", "ablation", "render", "export", "bench",
            "report", "convert-lpips", "clip-metrics", "view", "process-data", "train-editor"]


#: ``action=`` values whose flag collects a list of values.
LIST_ACTIONS = ("append", "extend")


class _RecordingGroup:
    """An argument group (or mutually exclusive group) of a :class:`OneLineParser` that
    records in its parser what is added through it; the rest is the group's."""

    def __init__(self, group, parser: "OneLineParser"):
        self._group, self._parser = group, parser

    def add_argument(self, *args, **kwargs) -> argparse.Action:
        return self._parser._record(self._group.add_argument(*args, **kwargs), kwargs)

    def add_mutually_exclusive_group(self, **kwargs) -> "_RecordingGroup":
        return _RecordingGroup(self._group.add_mutually_exclusive_group(**kwargs), self._parser)

    def __getattr__(self, name):
        return getattr(self._group, name)


class OneLineParser(argparse.ArgumentParser):
    """argparse, but errors are one line and exit with status 2.

    Every ``type=float`` flag of every command (and its config-file value) is read by
    :func:`finite_float`: no command has a use for an infinite or NaN number.

    Attributes:
      arguments: every argument added (on the parser or through its groups), in order
        (argparse keeps its own list private); ``-h`` is not among them.
      lists: those of them whose ``action`` collects a list (:data:`LIST_ACTIONS`).
      commands: {command: its parser}, the subcommands :func:`build_parser` added.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        for kind, reader in TYPE_READERS.items():
            self.register("type", kind, reader)
        # Set after argparse's own construction (its -h and its two default groups).
        self.arguments: list[argparse.Action] = []
        self.lists: set[argparse.Action] = set()
        self.commands: dict[str, OneLineParser] = {}

    def _recording(self) -> bool:
        return hasattr(self, "arguments")

    def _record(self, action: argparse.Action, kwargs: dict) -> argparse.Action:
        self.arguments.append(action)
        if kwargs.get("action") in LIST_ACTIONS or getattr(action, "collects", False):
            self.lists.add(action)
        return action

    def add_argument(self, *args, **kwargs) -> argparse.Action:
        action = super().add_argument(*args, **kwargs)
        return self._record(action, kwargs) if self._recording() else action

    def add_argument_group(self, *args, **kwargs):
        group = super().add_argument_group(*args, **kwargs)
        return _RecordingGroup(group, self) if self._recording() else group

    def add_mutually_exclusive_group(self, **kwargs):
        group = super().add_mutually_exclusive_group(**kwargs)
        return _RecordingGroup(group, self) if self._recording() else group

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def _module(name: str):
    return importlib.import_module(f"experiments.{name.replace('-', '_')}")


def add_shared_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=None, help="run directory for all outputs")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random draw")
    parser.add_argument("--config", type=Path, default=None,
                        help="JSON or TOML file setting any flag by name (command line wins)")
    parser.add_argument("--device", default=None,
                        help="JAX platform to run on (cpu, gpu); default: JAX's choice")
    parser.add_argument("--quiet", action="store_true", help="no progress bars, log lines only")


PROG = "python -m experiments"


def _add_command_arguments(p: OneLineParser, mod) -> OneLineParser:
    """``p`` with command module ``mod``'s flags: the shared ones, then its own."""
    add_shared_arguments(p)
    mod.add_arguments(p)
    p.set_defaults(_module=mod)
    return p


@functools.cache
def build_parser(only: str | None = None) -> OneLineParser:
    """The command line's parser, built once per process (every command module imported,
    every flag generated); its ``commands`` are the subcommands' parsers. ``only``: the
    parser of a command line that names that command (no other command's module imported).

    Nothing changes it once built: :func:`parse` gives a config file's values to a parser
    of the one command, built for that parse (:func:`_parser_with_config`)."""
    parser = OneLineParser(prog=PROG,
                           description="jaxedit: progressive 3DGS scene editing (ProEdit) in JAX")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    for name in COMMANDS if only is None else [only]:
        try:
            mod = _module(name)
        except ModuleNotFoundError as e:
            if e.name != f"experiments.{name.replace('-', '_')}":
                raise
            continue
        parser.commands[name] = _add_command_arguments(
            sub.add_parser(name, help=mod.HELP, description=mod.HELP), mod)
    return parser


def command_parser(command: str) -> OneLineParser:
    """The parser of subcommand ``command`` (the one :func:`parse` reads it with)."""
    return build_parser(command).commands[command]


def _parser_with_config(command: str, values: dict) -> OneLineParser:
    """A parser of ``command`` alone, built for one parse, whose defaults are a config
    file's ``values`` ({dest: value}) and whose flags those values set are not required.
    Changing it changes no other parse (the process's :func:`build_parser` is untouched)."""
    p = _add_command_arguments(OneLineParser(prog=f"{PROG} {command}",
                                             description=_module(command).HELP),
                               _module(command))
    p.set_defaults(command=command, **values)
    for action in p.arguments:
        if action.dest in values:
            action.required = False
    return p


def parse(argv: list[str]) -> argparse.Namespace:
    """The flags of ``argv``, over ``--config``'s values, over the command's defaults.

    Without ``--config`` the process's parser of the command (:func:`build_parser`) reads ``argv``;
    with it, the file's values (checked as their flags' command-line text would be,
    :func:`config_values`) are the defaults of a parser of that command built for this
    parse. No parser is changed after it is built, so parses never see each other's files.
    """
    command = argv[0] if argv else None
    parser = build_parser(command if command in COMMANDS else None)
    config = _config_file(argv[1:]) if command in parser.commands else None
    values = {}
    if config is None:
        args = parser.parse_args(argv)
        if args.command is None:
            parser.print_help()
            parser.exit(2)
    else:
        values = config_values(parser.commands[command], load_config(config), config)
        args = _parser_with_config(command, values).parse_args(argv[1:])
    # Flags set by the config file count as given (experiments/flags.py builds the config
    # tree from the given flags over the command's own defaults).
    setattr(args, GIVEN, set(getattr(args, GIVEN, ())) | set(values))
    return args


def main(argv: list[str] | None = None, *, preloaded=None) -> int:
    """Run the command ``argv``; its exit status. ``preloaded``: an
    :class:`experiments.edit.Preloaded` that keeps a steering command's inputs for the next
    command of this process (the viewer's warm worker)."""
    from jaxedit import DataError

    argv = sys.argv[1:] if argv is None else argv
    args = None
    dist = None
    result_out = sys.stdout
    try:
        args = parse(argv)
        args._preloaded = preloaded
        dist = distributed_config(args)
        if dist is not None and not _is_worker():
            return supervised(argv, args, dist)
        if args.device:
            import jax
            jax.config.update("jax_platforms", args.device)
        # The commands compile once across runs and record what they compiled; a bad
        # JAXEDIT_COMPILE_CACHE_MB or _MIN_S is one line.
        from jaxedit.compilation import enable
        enable()
        if dist is not None:
            from jaxedit.parallel.distributed import check_agreement, initialize, is_writer

            result_out = _stdout_for_the_result()
            initialize(dist)
            # Before any work, every process must have been given the same run (process 0
            # checks and writes --out for all): one line where they differ, not a silent run.
            check_agreement({k: jsonable(v) for k, v in vars(args).items() if not
                             k.startswith("_") and k not in ("process_id", "quiet", "config")},
                            dist.init_timeout)
            args._writer = is_writer()
            args.quiet = args.quiet or not args._writer  # one process reports progress
        check_paths(args, command_parser(args.command).arguments, outputs=writes(args))
        # A command that builds its output folder whole (staged beside it, renamed into
        # place: process-data) must find it absent or empty: it takes no lock inside it
        # and records its config once it succeeded.
        whole = getattr(args._module, "RECORD_CONFIG_AFTER_RUN", False)
        # A command may only signal a run (no lock, no record) or add to it (the lock, the
        # run's own config.json kept): the module's out_use(args) says ("run" by default).
        use = getattr(args._module, "out_use", lambda a: "run")(args)
        args._argv = list(argv)
        with claimed_out(None if whole or not writes(args) or use == "signal" else args.out):
            if not whole and writes(args) and use == "run":
                write_run_config(args, argv)
            result = args._module.run(args)
        if whole:
            write_run_config(args, argv)
        if dist is not None:
            from jaxedit.parallel.distributed import barrier

            barrier("jaxedit-command-done")  # the others wait for the writer's last files
    except DataError as e:
        print(f"error: {named_by_flag(e, args)}", file=sys.stderr)
        return _failed(dist)
    except OSError as e:
        refused = write_refused(e, getattr(args, "out", None))
        if refused is None:
            raise
        print(f"error: {refused}", file=sys.stderr)
        return _failed(dist)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    if result and writes(args):
        print(json.dumps(jsonable(result), indent=2), file=result_out, flush=True)
    # What a command does once --out is released (edit --view: the viewer serves on).
    after = getattr(args._module, "after_release", None)
    if after is not None:
        after(args)
    return 0


def named_by_flag(error, args: argparse.Namespace | None):
    """``error`` with the config field it names replaced by the command's flag for it.

    The library's errors name fields (``max_seconds``); the user typed flags
    (``--max-subtask-seconds``). The mapping is generated from the command's config
    tree (its module's ``FLAGS``, see experiments/flags.py), its parser's dests and,
    for a library argument named unlike its flag, the module's ``FIELD_FLAGS``. An
    error about a file or folder the user gave says with which flag.
    """
    from jaxedit import DataError

    if args is None or getattr(args, "command", None) is None:
        return error
    sub = command_parser(args.command)
    names = flag_names(*getattr(args._module, "FLAGS", ()), actions=sub.arguments)
    named = as_flags(error, names | getattr(args._module, "FIELD_FLAGS", {}))
    if named is not error or error.where is None:
        return named
    for action in sub.arguments:
        value = getattr(args, action.dest, None)
        if (action.option_strings and isinstance(value, (str, Path)) and str(value) == error.where
                and action.option_strings[-1] not in error.problem):
            return DataError(error.where, f"{error.problem} (given as {action.option_strings[-1]})")
    return error
