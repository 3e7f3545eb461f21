"""A command run as several processes (:mod:`jaxedit.parallel.distributed`): its flags, its
config, and the supervisor that turns a lost peer into one line and cleans ``--out``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from .flags import Flag, FlagSet
from .rundirs import KEPT_RECORD, _first_missing, remove_created


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
