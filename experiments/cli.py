"""Subcommand dispatch, shared flags, config files and run directories.

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

Before any work starts, :func:`check_paths` checks every path flag (inputs exist,
``--out``/``--output`` can be created and written) and :func:`config_values` puts
every config-file value through its flag's own argparse conversion, so a config
file gets exactly the validation the command line gets. While a command runs it
holds a lock on ``--out`` (a second process on the same folder is refused), and a
run that ends in a DataError removes what it had created there.

``edit`` and ``reconstruct`` also take ``--coordinator HOST:PORT --num-processes N
--process-id I`` (:class:`jaxedit.parallel.distributed.DistributedConfig`): each process then runs
as a supervised worker (:func:`supervised`), joins ``jax.distributed``, and only process 0
checks, locks and writes ``--out``.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import errno
import functools
import json
import os
import shutil
import sys
import tempfile
import tomllib
from pathlib import Path

# finite_float (re-exported), TYPE_READERS: how a flag's type reads its text.
from .flags import (COMMA_READERS, GIVEN, TYPE_READERS, Flag, FlagSet, as_flags, comma_list,  # noqa: F401
                    finite_float, flag_names)

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


def load_config(path: Path) -> dict:
    from jaxedit import DataError

    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as e:
        raise DataError(path, f"cannot read config file ({e.strerror or e})") from None
    except UnicodeDecodeError as e:
        raise DataError(path, f"config file is not UTF-8 text (byte {e.start})") from None
    try:
        if str(path).endswith(".toml"):
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as e:
        raise DataError(path, f"malformed config ({e})") from None
    except RecursionError:
        raise DataError(path, "malformed config (nested too deeply)") from None
    if not isinstance(data, dict):
        raise DataError(path, "config must be a table/object of flag names to values")
    return {k.replace("-", "_"): v for k, v in data.items()}


PROG = "python -m experiments"


def _add_command_arguments(p: OneLineParser, mod) -> OneLineParser:
    """``p`` with command module ``mod``'s flags: the shared ones, then its own."""
    add_shared_arguments(p)
    mod.add_arguments(p)
    p.set_defaults(_module=mod)
    return p


@functools.cache
def build_parser() -> OneLineParser:
    """The command line's parser, built once per process (every command module imported,
    every flag generated); its ``commands`` are the subcommands' parsers.

    Nothing changes it once built: :func:`parse` gives a config file's values to a parser
    of the one command, built for that parse (:func:`_parser_with_config`)."""
    parser = OneLineParser(prog=PROG,
                           description="jaxedit: progressive 3DGS scene editing (ProEdit) in JAX")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    for name in COMMANDS:
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
    """The parser of subcommand ``command`` (of the process's one :func:`build_parser`)."""
    return build_parser().commands[command]


def jsonable(value):
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    return value


def write_run_config(args: argparse.Namespace, argv: list[str] | None = None) -> None:
    """Record the resolved flags, the command line ``argv`` (default: this process's) and
    the version in ``args.out/config.json``."""
    import jaxedit
    from jaxedit.io.files import atomic_write_text

    if args.out is None:
        return
    args.out.mkdir(parents=True, exist_ok=True)
    flags = {k: jsonable(v) for k, v in vars(args).items() if not k.startswith("_")}
    record = {"command": args.command, "jaxedit_version": jaxedit.__version__, "flags": flags,
              "argv": sys.argv[1:] if argv is None else [str(a) for a in argv]}
    atomic_write_text(args.out / "config.json", json.dumps(record, indent=2) + "\n")


def _flag_name(action: argparse.Action) -> str:
    """How the user names a flag: its long option, or a positional's metavar."""
    if action.option_strings:
        return action.option_strings[-1]
    return action.metavar if isinstance(action.metavar, str) else action.dest.upper()


def config_value(sub: argparse.ArgumentParser, action: argparse.Action, value, path: Path):
    """A config-file value converted and checked exactly as its flag's command-line text is.

    The value is turned back into the token(s) a user would type and put through the
    action's own type and choices (argparse's conversion), so ``"iters": "abc"``, a
    list for a one-value flag or ``true`` for a number fail just as on the command line.
    ``null`` is accepted only where the flag's default is unset (it means "not given").
    """
    from jaxedit import DataError

    name = _flag_name(action)
    if value is None:
        if action.default is None:
            return None
        raise DataError(path, f"{action.dest}: null is not a value of {name}")
    if action.nargs == 0:  # store_true / store_false / store_const switches
        if not isinstance(value, bool):
            raise DataError(path, f"{action.dest}: {name} is a switch, expected true or false, "
                            f"got {value!r}")
        return value
    items = str if action.type is comma_list else (str, int, float)
    if action.type in COMMA_READERS and isinstance(value, list) and all(
            isinstance(v, items) and not isinstance(v, bool) for v in value):
        value = ",".join(map(str, value))  # config.json records a comma-separated flag as a list
    many = action in sub.lists or action.nargs in ("+", "*") or isinstance(action.nargs, int)
    values = value if many and isinstance(value, list) else [value]
    if many and not isinstance(value, list):
        raise DataError(path, f"{action.dest}: {name} takes a list, got {value!r}")
    if isinstance(action.nargs, int) and len(values) != action.nargs:
        raise DataError(path, f"{action.dest}: {name} takes {action.nargs} values, "
                        f"got {len(values)}")
    if action.nargs == "+" and not values:
        raise DataError(path, f"{action.dest}: {name} takes at least one value")
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (str, int, float)):
            raise DataError(path, f"{action.dest}: {name} expects a "
                            f"{'list of ' if many else ''}single value as typed on the "
                            f"command line, got {json.dumps(v)[:40]}")
    try:
        converted = [convert(action, str(v)) for v in values]
    except argparse.ArgumentError as e:
        raise DataError(path, f"{action.dest}: {e}") from None
    return converted if many else converted[0]


def convert(action: argparse.Action, text: str):
    """``text`` read as one command-line value of ``action``: its type (as
    :class:`OneLineParser` reads it, :data:`TYPE_READERS`) and its choices, refused with
    argparse's own messages (an ``ArgumentError`` naming the flag)."""
    reader = str if action.type is None else TYPE_READERS.get(action.type, action.type)
    try:
        value = reader(text)
    except argparse.ArgumentTypeError as e:
        raise argparse.ArgumentError(action, str(e)) from None
    except (TypeError, ValueError):
        name = getattr(action.type, "__name__", repr(action.type))
        raise argparse.ArgumentError(action, f"invalid {name} value: {text!r}") from None
    if action.choices is not None and value not in action.choices:
        choices = ", ".join(map(repr, action.choices))
        raise argparse.ArgumentError(action, f"invalid choice: {value!r} (choose from {choices})")
    return value


def _flat(config: dict, flags, prefix: str = "") -> dict:
    """A config file's tables flattened to dotted keys (``[train.densify]`` ->
    ``train.densify.grad_threshold``). A dict under a flag's own name, or an empty one, is
    a value (which the flag then refuses), not a table."""
    out = {}
    for k, v in config.items():
        if isinstance(v, dict) and v and prefix + k not in flags:
            out.update(_flat(v, flags, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


def config_values(sub: argparse.ArgumentParser, config: dict, path: Path) -> dict:
    """{dest: value} of a config file, each checked by :func:`config_value`. A key is a
    flag's dest or a setting's path in the command's config tree (nested tables or dotted
    keys: ``train.densify.grad_threshold``)."""
    from jaxedit import DataError

    actions = {}
    for a in sub.arguments:
        if a.dest not in ("help", "config"):
            actions.setdefault(a.dest, a)
    module = sub.get_default("_module")
    paths = {}
    for flag_set in getattr(module, "FLAGS", ()):
        paths.update(flag_set.keys())
    config = {paths.get(k, k) if k not in actions else k: v
              for k, v in _flat(config, set(actions) | set(paths)).items()}
    unknown = sorted(set(config) - set(actions))
    if unknown:
        raise DataError(path, f"unknown flag(s) {', '.join(unknown)} for {sub.prog.split()[-1]}")
    return {k: config_value(sub, actions[k], v, path) for k, v in config.items()}


def _config_file(argv: list[str]) -> Path | None:
    """The ``--config`` of a command's flags ``argv`` (the last one given), read alone:
    the full parse may need the file's values first (a required flag it sets)."""
    pre = argparse.ArgumentParser(add_help=False)  # abbreviations as the full parse reads them
    pre.add_argument("--config", type=Path, default=None)
    return pre.parse_known_args(argv)[0].config


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

    Without ``--config`` the process's one parser (:func:`build_parser`) reads ``argv``;
    with it, the file's values (checked as their flags' command-line text would be,
    :func:`config_values`) are the defaults of a parser of that command built for this
    parse. No parser is changed after it is built, so parses never see each other's files.
    """
    parser = build_parser()
    command = argv[0] if argv else None
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


#: Path flags that name outputs (everything else of type Path is an input that must exist).
OUTPUT_DIRS = ("out",)
OUTPUT_FILES = ("output",)


def _check_utf8(path: Path, name: str) -> None:
    from jaxedit import DataError

    try:
        os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        raise DataError(name, f"path {os.fsencode(path)!r} is not valid UTF-8; "
                        "use a UTF-8 name") from None


def check_output_path(path: Path, name: str, *, directory: bool = True) -> None:
    """Refuse, before any work, an output that cannot be created or written.

    Args:
      path: the folder (``directory``) or file to write.
      name: the flag, for the message.
    """
    from jaxedit import DataError

    _check_utf8(path, name)
    path = Path(path)
    if path.exists():
        if directory and not path.is_dir():
            raise DataError(name, f"{path} exists and is not a directory")
        if not directory and path.is_dir():
            raise DataError(name, f"{path} is a directory, expected a file name")
        if directory and (path / "config.json").is_dir():  # every run records itself there
            raise DataError(name, f"{path / 'config.json'} is a folder, where the run records "
                                  f"its settings; move it or choose another {name}")
    existing = path if directory and path.is_dir() else path.parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise DataError(name, f"cannot create {path}: {existing} is a file, not a directory")
    try:  # a real write: permission bits, read-only mounts and root all answer truthfully
        fd, probe = tempfile.mkstemp(prefix=".jaxedit-probe-", dir=existing)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise DataError(name, f"{path}: cannot write in {existing} ({e.strerror or e})") from None


def check_input_path(path: Path, name: str) -> None:
    from jaxedit import DataError

    _check_utf8(path, name)
    if not Path(path).exists():
        raise DataError(path, f"does not exist (given as {name})")
    if not os.access(path, os.R_OK):
        raise DataError(path, f"is not readable (given as {name})")


def check_paths(args: argparse.Namespace, *, outputs: bool = True) -> None:
    """Check every path flag of the command (inputs exist, outputs can be made) up front;
    ``outputs`` False: inputs only (a process that writes nothing, :func:`writes`)."""
    for action in command_parser(args.command).arguments:
        value = getattr(args, action.dest, None)
        if action.type is not Path or value is None or action.dest == "config":
            continue
        name = _flag_name(action)
        if action.dest in OUTPUT_DIRS + OUTPUT_FILES and not outputs:
            continue
        if action.dest in OUTPUT_DIRS:
            check_output_path(value, name)
        elif action.dest in OUTPUT_FILES:
            check_output_path(value, name, directory=False)
        else:
            check_input_path(value, name)


def _first_missing(path: Path) -> Path | None:
    """The outermost folder of ``path`` that does not exist yet (None: it all exists)."""
    path = Path(os.path.abspath(path))
    missing = None
    while not path.exists():
        missing, path = path, path.parent
    return missing


#: OSError numbers of a write the machine refused (full disk, quota, read-only, too large):
#: the environment's fault, reported as one line like bad input.
WRITE_REFUSED = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG)


def write_refused(error: OSError, out: Path | None):
    """The :class:`jaxedit.DataError` of a refused write (None for other OS errors).

    Names the file when the OS did, else the output folder ``out``.
    """
    from jaxedit import DataError

    if error.errno not in WRITE_REFUSED:
        return None
    return DataError(error.filename or out, f"cannot write ({os.strerror(error.errno)}); "
                                            f"what this command wrote there was removed")


@contextlib.contextmanager
def claimed_out(out: Path | None):
    """Hold ``out``'s lock while the command runs; on a failure remove what it created.

    A failure is a DataError or a refused write (:func:`write_refused`, raised as a
    DataError). Entries of ``out`` that existed before (a resumed run's checkpoints) are
    kept, and its ``config.json`` is put back as it was: a failed command leaves the
    record of the run alone. A DataError whose ``record`` names a file under ``out`` (the
    editor identity check's ``identity.json``) keeps that file: the record of why it stopped.
    """
    from jaxedit import DataError
    from jaxedit.io.files import LOCK_NAME, folder_lock

    if out is None:
        yield
        return
    created = _first_missing(out)
    before = None if created is not None else set(os.listdir(out))
    with folder_lock(out, flag="--out"), _record_kept(Path(out) / "config.json"):
        try:
            try:
                yield
            except OSError as e:
                refused = write_refused(e, out)
                if refused is None:
                    raise
                raise refused from None
        except DataError as e:
            remove_created(out, created, before, keep={LOCK_NAME, KEPT_RECORD},
                           record=getattr(e, "record", None))
            raise


def remove_created(out: Path, created: Path | None, before: set | None, *,
                   keep: set = frozenset(), record: Path | None = None) -> None:
    """Remove what a failed command created under ``out``: ``created`` (the outermost
    folder it made, :func:`_first_missing`), else the entries not in ``before`` (the
    listing before it ran) nor in ``keep``. ``record``, a file the failure wrote on
    purpose, stays (with the folders above it)."""
    record = None if record is None else Path(os.path.abspath(record))
    if created is not None:
        _remove_all_but(Path(os.path.abspath(created)), record)
        return
    for name in set(os.listdir(out)) - before - set(keep):
        _remove_all_but(Path(os.path.abspath(Path(out) / name)), record)


def _remove_all_but(target: Path, record: Path | None) -> None:
    """Remove ``target`` (a file or a folder) except ``record`` and the folders above it."""
    if record is not None and record == target:
        return
    if target.is_dir() and not target.is_symlink():
        if record is not None and target in record.parents:
            for entry in target.iterdir():
                _remove_all_but(entry, record)
        else:
            shutil.rmtree(target, ignore_errors=True)
    else:
        target.unlink(missing_ok=True)


KEPT_RECORD = ".config.json.kept"


@contextlib.contextmanager
def _record_kept(record: Path):
    """Put ``record`` back as it was if the block fails with a DataError.

    The old file stays hard-linked under a hidden name meanwhile (the new record is
    written beside it and renamed over it), so putting it back is a rename: it needs
    no free space, which a full disk would not give.
    """
    from jaxedit import DataError

    kept = record.with_name(KEPT_RECORD)
    had = record.is_file()
    if had:
        kept.unlink(missing_ok=True)
        os.link(record, kept)
    try:
        yield
    except DataError:
        if had:
            os.replace(kept, record)
        raise
    finally:
        kept.unlink(missing_ok=True)


def main(argv: list[str] | None = None) -> int:
    from jaxedit import DataError

    argv = sys.argv[1:] if argv is None else argv
    args = None
    dist = None
    result_out = sys.stdout
    try:
        args = parse(argv)
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
        check_paths(args, outputs=writes(args))
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


def _stdout_for_the_result():
    """A stream on this process's stdout kept for the command's result; what else writes to
    file descriptor 1 from now on goes to stderr.

    The distributed runtime's C++ code (gloo) prints its connection notices to stdout, from
    several threads at once and interleaved mid-line, so no filter of stdout's lines could
    keep the result JSON whole (a leaked half-notice broke a two-process run's JSON).
    """
    sys.stdout.flush()
    stream = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    return stream


# --- several processes (jaxedit.parallel.distributed) -------------------------------------------

def distributed_flags():
    """The flags of :class:`jaxedit.parallel.distributed.DistributedConfig` (``--coordinator``,
    ``--num-processes``, ``--process-id``, ``--init-timeout``, ``--heartbeat-timeout``),
    for a command's ``FLAGS``."""
    from jaxedit.parallel.distributed import DistributedConfig

    return FlagSet(DistributedConfig, (
        Flag("coordinator"), Flag("num_processes"), Flag("process_id"),
        Flag("init_timeout"), Flag("heartbeat_timeout"))).complete()


def distributed_config(args: argparse.Namespace):
    """The command's :class:`jaxedit.parallel.distributed.DistributedConfig` when it joins a
    multi-process run (``--coordinator`` given), else None."""
    from jaxedit.parallel.distributed import DistributedConfig

    for flags in getattr(args._module, "FLAGS", ()):
        if flags.root is DistributedConfig:
            config = flags.build(args)
            return config if config.active else None
    return None


def _is_worker() -> bool:
    from jaxedit.parallel.distributed import WORKER_ENV

    return os.environ.get(WORKER_ENV) == "1"


def writes(args: argparse.Namespace) -> bool:
    """Whether this process writes the command's outputs (in a multi-process run only
    process 0 does; the others write nothing)."""
    return getattr(args, "_writer", True)


def supervised(argv: list[str], args: argparse.Namespace, dist) -> int:
    """Run this command as a worker (:func:`jaxedit.parallel.distributed.supervise`): a lost peer or
    coordinator, which the runtime answers with an abort, becomes one line and status 2,
    and the writer's supervisor removes what the run created in ``--out``."""
    from jaxedit.parallel.distributed import supervise

    out = args.out if dist.process_id == 0 and dist.coordinator != "auto" else None
    created = before = None
    if out is not None:
        created = _first_missing(out)
        before = None if created is not None else set(os.listdir(out))

    def cleanup():
        if out is None or not Path(out).exists():
            return
        kept = Path(out) / KEPT_RECORD
        if kept.exists():  # the worker's config.json replaced the record: put it back
            os.replace(kept, Path(out) / "config.json")
        remove_created(out, created, before)

    return supervise([sys.executable, "-m", "experiments", *argv], dist, cleanup=cleanup)


def _failed(dist) -> int:
    """Exit status 2; a worker of a multi-process run leaves at once (its peers learn of it
    from the runtime's heartbeats) rather than wait at the runtime's shutdown barrier."""
    if dist is not None:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(2)
    return 2


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


def require_memory(flag: str, needed: float, what: str) -> None:
    """Refuse up front a run whose estimated working set exceeds the free memory: the
    library's one check (:func:`jaxedit.memory.require_memory`), which its readers use too."""
    from jaxedit.memory import require_memory as check

    check(flag, needed, what)
