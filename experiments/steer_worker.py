"""The viewer's warm worker: the steering commands of one edit run, one after another, in a
process that has imported jaxedit, read the run's views, input scene and editor, and
prepared a refine of its last step (its programs compiled or read back) before the first
command arrives. :class:`experiments.view.WarmWorker` starts it with the viewer.

    python -m experiments.steer_worker RUN

Reads one command per line on stdin, as JSON: ``{"argv": ["edit", "--out", RUN, ...]}``
(the arguments of ``python -m experiments``). Each command's messages go to stderr as the
command line's would; :data:`READY` follows the warm-up, and ``EXIT`` + the command's exit
status follows each command. Its results (stdout) are dropped, as the viewer drops a
command line's. It ends at the end of stdin.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import traceback
from pathlib import Path

from .view import WORKER_EXIT as EXIT, WORKER_READY as READY  # the viewer reads them


def run_command(argv: list[str], preloaded) -> int:
    """``python -m experiments ARGV`` in this process; its exit status."""
    from . import cli

    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        try:
            return int(cli.main(argv, preloaded=preloaded) or 0)
        except SystemExit as e:  # the parser's one-line errors
            return e.code if isinstance(e.code, int) else 1
        except Exception:  # a bug: its traceback, as the command line would print it
            traceback.print_exc()
            return 1


def serve(run_dir: Path, commands=None, messages=None) -> int:
    """Warm up on ``run_dir``, then run each command line of ``commands`` (stdin)."""
    from jaxedit import DataError
    from jaxedit.compilation import enable

    from .edit import Preloaded, warm_steering

    commands = sys.stdin if commands is None else commands
    messages = sys.stderr if messages is None else messages
    preloaded = Preloaded()
    try:
        enable()
        warm_steering(Path(run_dir), preloaded)
    except DataError as e:  # the first command says it again, naming its flag
        print(f"warm-up skipped: {e}", file=messages, flush=True)
    except Exception as e:  # noqa: BLE001  the commands run cold, and say what is wrong
        print(f"warm-up failed: {type(e).__name__}: {e}", file=messages, flush=True)
    print(READY, file=messages, flush=True)
    for line in commands:
        try:
            argv = [str(a) for a in json.loads(line)["argv"]]
        except (ValueError, KeyError, TypeError) as e:
            print(f"error: the worker's command is not JSON with an argv ({e})",
                  file=messages, flush=True)
            status = 2
        else:
            status = run_command(argv, preloaded)
        print(f"{EXIT}{status}", file=messages, flush=True)
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        print("usage: python -m experiments.steer_worker RUN", file=sys.stderr)
        sys.exit(2)
    sys.exit(serve(Path(sys.argv[1])))
