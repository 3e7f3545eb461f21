"""Config files of the commands: ``--config FILE`` (JSON or TOML) read and every value put
through its flag's own argparse conversion (:func:`config_values`), so a file gets exactly
the validation the command line gets; and ``config.json``, each run's record of its
resolved flags (:func:`write_run_config`).
"""

from __future__ import annotations

import argparse
import json
import sys
import tomllib
from pathlib import Path

from .flags import COMMA_READERS, TYPE_READERS, comma_list


def load_config(path: Path) -> dict:
    """{dest: value} of a JSON or TOML config file (dashes in its keys become underscores).

    Raises:
      DataError naming ``path``: unreadable, not UTF-8, malformed, or not a table.
    """
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


def flag_label(action: argparse.Action) -> str:
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

    name = flag_label(action)
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
