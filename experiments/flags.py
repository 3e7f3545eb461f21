"""Command-line flags generated from a command's frozen config tree.

A command's settings are declared once, as fields of frozen dataclasses (the library's
:class:`jaxedit.train.TrainConfig`, :class:`jaxedit.densify.DensifyConfig`,
:class:`jaxedit.edit.plan.ProEditConfig`, ...). A :class:`Flag` names one field by its
dotted path in the tree; :class:`FlagSet` turns a tree's flags into argparse arguments
whose type, default and help come from the field (the help from the owner's docstring
``Attributes:`` section), builds the tree back from the parsed flags, and maps the
fields the library's errors name to the flags a user typed (:meth:`FlagSet.flag_of`).

So a default or a range changes in one place, the dataclass (a range is the field's
metadata, :func:`jaxedit.errors.ranged`), and the command line follows.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Sequence

from jaxedit.errors import field_range

#: Namespace attribute of the dests set on the command line or by ``--config``.
GIVEN = "_given"


@dataclasses.dataclass(frozen=True)
class Flag:
    """One generated flag.

    Attributes:
      field: dotted path of the field in the tree, e.g. ``"train.densify.stop_at"``.
      name: the flag (default ``--`` and the field's own name with dashes).
      off: for a boolean field, the flag that sets it False (``--sync`` of ``--async``).
      choices: the values a string field takes.
      key: the name a ``--config`` file and config.json use (default: the flag's, with
        underscores).
      repeat: for a ``tuple[str, ...]`` field: the flag is given once per item (a list in
        a ``--config`` file), not as one comma-separated value.
      group: title of the help section the flag is listed under (None: the command's).
      required: the command refuses to run without it (unless ``--config`` sets it); in an
        ``exclusive`` group whose flags are all required: one of them is.
      exclusive: name of a group of flags of which at most one may be given.
      const: the value of the flag given without one (the flag's value is then optional).
      metavar: the value's name in the help (default: the flag's in capitals).
    """

    field: str
    name: str | None = None
    off: str | None = None
    choices: tuple | None = None
    key: str | None = None
    repeat: bool = False
    group: str | None = None
    metavar: str | tuple | None = None
    required: bool = False
    exclusive: str | None = None
    const: Any = None

    @property
    def flag(self) -> str:
        return self.name or "--" + self.field.rsplit(".", 1)[-1].replace("_", "-")

    @property
    def dest(self) -> str:
        return self.key or self.flag[2:].replace("-", "_")


class _Given(argparse.Action):
    """Store (or store a constant), and record that the flag was given."""

    #: Whether the flag collects a list (one item each time it is given).
    collects = False

    def __init__(self, option_strings, dest, const=None, nargs=None, **kwargs):
        self.switch = const is not None and nargs is None  # a const with nargs="?": optional
        super().__init__(option_strings, dest, nargs=0 if self.switch else nargs, const=const,
                         **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, self.const if self.switch else values)
        given = set(getattr(namespace, GIVEN, ()))
        setattr(namespace, GIVEN, given | {self.dest})


class _GivenEach(_Given):
    """Add the value to the tuple of those given before (a new tuple: the default is
    shared by every parse), and record that the flag was given."""

    collects = True

    def __call__(self, parser, namespace, values, option_string=None):
        super().__call__(parser, namespace, (*(getattr(namespace, self.dest) or ()), values),
                         option_string)


def finite_float(text: str) -> float:
    """argparse's ``type=float``, refusing inf and nan (argparse then names the flag)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def guidance_pair(text: str) -> tuple[float, float]:
    """A script's ``--guidance TEXT,IMAGE`` (one argument, comma-separated): the scales
    :func:`jaxedit.editors.diffusion.check_guidance` accepts, as ``edit --guidance``."""
    from jaxedit.editors.diffusion import check_guidance
    from jaxedit.errors import DataError

    try:
        return check_guidance(text.split(","))
    except DataError as e:
        raise argparse.ArgumentTypeError(f"want TEXT,IMAGE: {e.problem}") from None


#: How :class:`experiments.cli.OneLineParser` reads a flag's ``type`` where it differs from
#: the type itself
#: (registered with argparse by :class:`experiments.cli.OneLineParser`, and used by
#: :func:`experiments.cli.convert` for config-file values and :meth:`FlagSet.field_value`).
TYPE_READERS = {float: finite_float}


def attribute_docs(cls: type) -> dict[str, str]:
    """{attribute: its text} from ``cls``'s docstring ``Attributes:`` section.

    An entry is ``name: text`` or ``a, b, c: text`` (shared by the names), continued on
    more deeply indented lines; text is joined into one line.
    """
    doc = inspect.getdoc(cls) or ""
    docs: dict[str, str] = {}
    lines = doc.split("\n")
    try:
        start = lines.index("Attributes:") + 1
    except ValueError:
        return docs
    names: list[str] = []
    indent = None
    for line in lines[start:]:
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        if depth == 0:
            break
        if indent is None:
            indent = depth
        m = re.match(r"\s*([A-Za-z_][\w, ]*):\s*(.*)$", line)
        if depth == indent and m:
            names = [n.strip() for n in m.group(1).split(",")]
            for n in names:
                docs[n] = m.group(2).strip()
        elif names:
            for n in names:
                docs[n] = f"{docs[n]} {line.strip()}".strip()
    return {k: _plain(v) for k, v in docs.items()}


def _plain(text: str) -> str:
    """Docstring markup as help text: ``x`` and :func:`x` become x."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", text)
    return text.replace("``", "")


def _owner_and_field(root: type, path: str) -> tuple[type, dataclasses.Field, Any]:
    """(dataclass owning the last component, its field, the field's default in the tree)."""
    cls, default = root, _default_instance(root)
    parts = path.split(".")
    for i, part in enumerate(parts):
        fields = {f.name: f for f in dataclasses.fields(cls)}
        if part not in fields:
            raise KeyError(f"{cls.__name__} has no field {part!r} ({path})")
        field = fields[part]
        value = getattr(default, part)
        if i == len(parts) - 1:
            return cls, field, value
        cls, default = typing.get_type_hints(cls)[part], value


def _default_instance(cls: type):
    return cls()


def comma_list(text: str) -> tuple[str, ...]:
    """A ``tuple[str, ...]`` field's flag value: comma-separated items, blanks dropped."""
    return tuple(t.strip() for t in str(text).split(",") if t.strip())


def comma_floats(text: str) -> tuple[float, ...]:
    """A ``tuple[float, ...]`` field's flag value: comma-separated numbers."""
    return tuple(finite_float(x) for x in comma_list(text))


def comma_ints(text: str) -> tuple[int, ...]:
    """A ``tuple[int, ...]`` field's flag value: comma-separated integers."""
    return tuple(int(x) for x in comma_list(text))


#: The readers of a tuple field given as one comma-separated value.
COMMA_READERS = (comma_list, comma_floats, comma_ints)


def _value_type(hint):
    """The parser of a field's annotation: its scalar type (``int | None`` -> int, a
    ``Path``), :func:`comma_list` for ``tuple[str, ...]``, or the item type of a tuple of
    fixed length (``tuple[float, float, float]``: three values, :func:`_count`)."""
    hint = _optional(hint)
    if hint in (int, float, str, bool, Path):
        return hint
    items = typing.get_args(hint)
    if typing.get_origin(hint) is tuple and items in ((str, ...), (float, ...), (int, ...)):
        return {str: comma_list, float: comma_floats, int: comma_ints}[items[0]]
    if (typing.get_origin(hint) is tuple and items and Ellipsis not in items
            and len(set(items)) == 1 and items[0] in (int, float, str)):
        return items[0]
    raise TypeError(f"no flag for a field of type {hint!r}")


def _optional(hint):
    """``X`` of ``X | None``."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return hint


def _count(hint) -> int | None:
    """How many values a fixed-length tuple field's flag takes (None: one value)."""
    hint = _optional(hint)
    items = typing.get_args(hint)
    if typing.get_origin(hint) is tuple and items and Ellipsis not in items:
        return len(items)
    return None


#: Help section of the flags :meth:`FlagSet.complete` generates for the fields without a name.
EVERY_SETTING = "every other setting, by its path in the config tree"


def leaf_fields(root: type, prefix: str = "") -> list[str]:
    """Dotted paths of the settings of config tree ``root`` (fields that are not dataclasses)."""
    out = []
    hints = typing.get_type_hints(root)
    for f in dataclasses.fields(root):
        hint = _optional(hints[f.name])
        if dataclasses.is_dataclass(hint):
            out += leaf_fields(hint, prefix + f.name + ".")
        else:
            out.append(prefix + f.name)
    return out


@dataclasses.dataclass(frozen=True)
class FlagSet:
    """The flags of one config tree ``root`` (a frozen dataclass whose fields may be
    dataclasses in turn).

    Attributes:
      root: the tree's dataclass.
      flags: its flags.
      derived: fields the command sets from another flag (e.g. a seed from the shared
        ``--seed``), which have no flag of their own here.
    """

    root: type
    flags: tuple[Flag, ...]
    derived: tuple[str, ...] = ()

    def complete(self) -> "FlagSet":
        """This set with a flag for every other setting of the tree, named by its path
        (``--train.densify.grad-threshold``; a switch also ``--no-...``), so that each one is
        reachable from the command line and from ``--config``."""
        named = {f.field for f in self.flags} | set(self.derived)
        extra = []
        for path in leaf_fields(self.root):
            if path in named:
                continue
            cls, field, _ = _owner_and_field(self.root, path)
            dashed = path.replace("_", "-")
            is_bool = _optional(typing.get_type_hints(cls)[field.name]) is bool
            extra.append(Flag(path, "--" + dashed, off="--no-" + dashed if is_bool else None,
                              key=path, group=EVERY_SETTING))
        return dataclasses.replace(self, flags=self.flags + tuple(extra))

    def keys(self) -> dict[str, str]:
        """{dotted field path: dest} of every flag: the nested keys ``--config`` takes."""
        return {f.field: f.dest for f in self.flags}

    def owner(self, flag: Flag) -> tuple[type, dataclasses.Field, Any]:
        return _owner_and_field(self.root, flag.field)

    def default(self, flag: Flag):
        """The flag's default: its field's default in the tree."""
        return self.owner(flag)[2]

    def add_to(self, parser: argparse.ArgumentParser) -> None:
        """Add every flag to ``parser`` (type, default, help from the field; a flag with a
        ``group`` to that help section of it)."""
        groups: dict[str, Any] = {}
        for flag in self.flags:
            target = parser
            if flag.group is not None:
                if flag.group not in groups:
                    groups[flag.group] = parser.add_argument_group(flag.group)
                target = groups[flag.group]
            if flag.exclusive is not None:
                key = ("exclusive", flag.exclusive)
                if key not in groups:
                    members = [f for f in self.flags if f.exclusive == flag.exclusive]
                    groups[key] = target.add_mutually_exclusive_group(
                        required=all(f.required for f in members))
                target = groups[key]
            self._add(flag, target)

    def _add(self, flag: Flag, parser) -> None:
        """Add one flag to ``parser`` (or a group of it)."""
        cls, field, default = self.owner(flag)
        hint = typing.get_type_hints(cls)[field.name]
        kind, count = _value_type(hint), _count(hint)
        doc = attribute_docs(cls).get(field.name)
        if doc is None:
            raise ValueError(f"{cls.__name__}.{field.name} has no entry in its docstring")
        text = doc.replace("%", "%%")
        if kind is bool:
            if flag.off is None:
                if default:
                    raise ValueError(f"{flag.flag}: a switch needs a default of False "
                                     "or an off flag")
                parser.add_argument(flag.flag, dest=flag.dest, action=_Given, const=True,
                                    default=False, help=text)
            else:
                group = parser.add_mutually_exclusive_group()
                group.add_argument(flag.flag, dest=flag.dest, action=_Given, const=True,
                                   default=default,
                                   help=f"{text}{' (default)' if default else ''}")
                group.add_argument(flag.off, dest=flag.dest, action=_Given, const=False,
                                   default=default,
                                   help=f"not {flag.flag}{'' if default else ' (default)'}")
            return
        if flag.repeat:
            if kind is not comma_list:
                raise ValueError(f"{flag.flag}: only a tuple[str, ...] field repeats")
            parser.add_argument(flag.flag, dest=flag.dest, action=_GivenEach, type=str,
                                default=default, metavar=flag.metavar,
                                help=f"{text} (repeatable)")
            return
        shown = ",".join(map(str, default)) if kind in COMMA_READERS and default else default
        if count is not None and default is not None:
            shown = " ".join(map(str, default))
        notes = [] if flag.required else [f"default: {shown}"]
        bounds = field_range(field)
        if bounds is not None:
            notes.append(bounds.describe())
        extra = {"nargs": count} if count is not None else {}
        if flag.const is not None:
            extra = {"nargs": "?", "const": flag.const}
        parser.add_argument(flag.flag, dest=flag.dest, action=_Given, type=kind,
                            default=default, choices=flag.choices, metavar=flag.metavar,
                            required=flag.required and flag.exclusive is None,
                            help=f"{text} ({'; '.join(notes)})" if notes else text, **extra)

    def values(self, args: argparse.Namespace) -> dict[str, Any]:
        """{field path: value} of the flags to apply: each one given (on the command line
        or in --config) or, for a namespace built by hand, each that differs from its
        field's default."""
        given = getattr(args, GIVEN, None)
        out = {}
        for flag in self.flags:
            value = getattr(args, flag.dest)
            if isinstance(value, list):
                value = tuple(value)  # a repeated flag's or a --config file's list
            if (flag.dest in given) if given is not None else value != self.default(flag):
                out[flag.field] = value
        return out

    def build(self, args: argparse.Namespace, bases: dict[str, Any] | None = None,
              derived: dict[str, Any] | None = None):
        """The config tree of ``args``: ``root()`` (with ``bases``, {top-level field:
        instance}, as the starting points of those subtrees) and the flags' values, plus
        ``derived`` {field path: value} that follow from them.

        The dataclasses check their fields as the tree is built (the ranges declared in
        the fields' metadata, :func:`jaxedit.errors.ranged`, and their own rules); the
        DataError of a field that has a flag here names the flag.
        """
        from jaxedit import DataError

        try:
            base = _replace(self.root(), {}, bases or {}) if bases else self.root()
            return with_fields(base, self.values(args) | (derived or {}))
        except DataError as e:
            raise as_flags(e, self.flag_of()) from None

    def field_value(self, name: str, text: str | None) -> tuple[str, Any]:
        """(field path, value) of this set's flag ``name`` (dashes optional) as the command
        line reads ``text`` (None: a switch given alone). ValueError with the reason if
        there is no such flag or the text is not one of its values."""
        wanted = "--" + name.lstrip("-")
        for flag in self.flags:
            cls, field, _ = self.owner(flag)
            kind = _value_type(typing.get_type_hints(cls)[field.name])
            if wanted not in (flag.flag, flag.off):
                continue
            if kind is bool:
                if text is not None:
                    raise ValueError(f"{wanted} is a switch and takes no value")
                return flag.field, wanted == flag.flag
            if text is None:
                raise ValueError(f"{wanted} needs a value")
            try:
                value = TYPE_READERS.get(kind, kind)(text)
            except (TypeError, ValueError, argparse.ArgumentTypeError) as e:
                raise ValueError(f"{wanted}: {e}") from None
            if flag.choices is not None and value not in flag.choices:
                raise ValueError(f"{wanted}: {value!r} is not one of {', '.join(flag.choices)}")
            return flag.field, value
        raise ValueError(f"{wanted} is not a setting of this command")

    def argv(self, config, base) -> list[str]:
        """The flags that turn tree ``base`` (what the command builds when they are not
        given) into tree ``config``: the command line of ``config``, for the record."""
        out: list[str] = []
        for flag in self.flags:
            path = flag.field.split(".")
            value, was = _get(config, path), _get(base, path)
            if value == was:
                continue
            cls, field, _ = self.owner(flag)
            kind = _value_type(typing.get_type_hints(cls)[field.name])
            if kind is bool:
                out.append(flag.flag if value else flag.off or "")
            elif flag.repeat:
                for item in value:
                    out += [flag.flag, item]
            elif isinstance(value, tuple) and kind not in COMMA_READERS:
                out += [flag.flag, *map(str, value)]
            elif value is None:
                raise ValueError(f"{flag.flag}: no command line unsets it (from {was!r})")
            else:
                out += [flag.flag, ",".join(map(str, value)) if kind in COMMA_READERS
                        else str(value)]
        if "" in out:
            raise ValueError("a switch without an off flag cannot be turned off")
        return out

    def flag_of(self) -> dict[str, str]:
        """{field name or dotted path: flag} for turning an error's field into a flag.

        A field's own name maps only where it is unambiguous in this set.
        """
        out: dict[str, str] = {}
        short: dict[str, set] = {}
        for flag in self.flags:
            out[flag.field] = flag.flag
            short.setdefault(flag.field.rsplit(".", 1)[-1], set()).add(flag.flag)
        out.update({k: next(iter(v)) for k, v in short.items() if len(v) == 1})
        return out


def _get(tree, path: list[str]):
    for part in path:
        tree = getattr(tree, part)
    return tree


def with_fields(tree, values: dict[str, Any]):
    """``tree`` with ``values`` ({dotted field path: value}) set; the dataclasses check
    the result as it is built."""
    changes: dict = {}
    for path, value in values.items():
        node = changes
        *parents, leaf = path.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return _replace(tree, changes, {})


def _replace(instance, changes: dict, bases: dict):
    """``instance`` with nested ``changes`` ({field: value or {subfield: ...}}) applied."""
    updates = {}
    for name in set(changes) | set(bases):
        current = bases.get(name, getattr(instance, name))
        change = changes.get(name)
        if isinstance(change, dict):
            updates[name] = _replace(current, change, {})
        elif name in changes:
            updates[name] = change
        else:
            updates[name] = current
    return dataclasses.replace(instance, **updates)


def flag_names(*sets: FlagSet, actions: Sequence[argparse.Action] = ()) -> dict[str, str]:
    """{field: flag} of ``sets``, and {dest: flag} of every other flag of ``actions`` (a
    command's parser's arguments, :attr:`experiments.cli.OneLineParser.arguments`)."""
    out: dict[str, str] = {}
    for action in actions:
        if action.option_strings and action.dest not in (argparse.SUPPRESS, "help"):
            out.setdefault(action.dest, action.option_strings[-1])
    for s in sets:
        out.update(s.flag_of())
    return out


def as_flags(error, names: dict[str, str]):
    """``error`` (a DataError) with the field it names replaced by its flag, if it has one."""
    from jaxedit import DataError

    where = getattr(error, "where", None)
    if where is None or where not in names:
        return error
    return DataError(names[where], error.problem)
