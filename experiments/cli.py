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
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import tomllib
from pathlib import Path

COMMANDS = ["demo", "make-scene", "reconstruct", "edit", "ablation", "render", "bench",
            "report", "convert-lpips", "clip-metrics", "view", "process-data"]


class OneLineParser(argparse.ArgumentParser):
    """argparse, but errors are one line and exit with status 2."""

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
        text = Path(path).read_text()
    except OSError as e:
        raise DataError(path, f"cannot read config file ({e.strerror or e})") from None
    try:
        if str(path).endswith(".toml"):
            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as e:
        raise DataError(path, f"malformed config ({e})") from None
    if not isinstance(data, dict):
        raise DataError(path, "config must be a table/object of flag names to values")
    return {k.replace("-", "_"): v for k, v in data.items()}


def build_parser() -> OneLineParser:
    parser = OneLineParser(prog="python -m experiments",
                           description="jaxedit: progressive 3DGS scene editing (ProEdit) in JAX")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    for name in COMMANDS:
        try:
            mod = _module(name)
        except ModuleNotFoundError as e:
            if e.name != f"experiments.{name.replace('-', '_')}":
                raise
            continue
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        add_shared_arguments(p)
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


def jsonable(value):
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    return value


def write_run_config(args: argparse.Namespace) -> None:
    """Record the resolved flags and version in ``args.out/config.json``."""
    import jaxedit
    from jaxedit.io.files import atomic_write_text

    if args.out is None:
        return
    args.out.mkdir(parents=True, exist_ok=True)
    flags = {k: jsonable(v) for k, v in vars(args).items() if not k.startswith("_")}
    record = {"command": args.command, "jaxedit_version": jaxedit.__version__, "flags": flags,
              "argv": sys.argv[1:]}
    atomic_write_text(args.out / "config.json", json.dumps(record, indent=2) + "\n")


def parse(argv: list[str]) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        parser.exit(2)
    if args.config is not None:
        sub = parser._subparsers._group_actions[0].choices[args.command]
        config = load_config(args.config)
        known = {a.dest for a in sub._actions}
        unknown = sorted(set(config) - known)
        if unknown:
            from jaxedit import DataError
            raise DataError(args.config, f"unknown flag(s) {', '.join(unknown)} for {args.command}")
        sub.set_defaults(**config)
        args = parser.parse_args(argv)
    return args


def main(argv: list[str] | None = None) -> int:
    from jaxedit import DataError

    argv = sys.argv[1:] if argv is None else argv
    try:
        args = parse(argv)
        if args.device:
            import jax
            jax.config.update("jax_platforms", args.device)
        # A command whose output folder must start empty records its config once it succeeded.
        after = getattr(args._module, "RECORD_CONFIG_AFTER_RUN", False)
        if not after:
            write_run_config(args)
        result = args._module.run(args)
        if after:
            write_run_config(args)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    if result:
        print(json.dumps(jsonable(result), indent=2))
    return 0
