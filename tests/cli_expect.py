"""What the bad-input tests expect of a refused command: exit status 2, one line on stderr
naming the problem, no traceback, and the user's folder as it was."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from experiments import cli


def listing(path: Path) -> list[str] | None:
    """The names under ``path`` (None when it does not exist): nothing created or removed."""
    return sorted(str(p.relative_to(path)) for p in path.rglob("*")) if path.exists() else None


def contents(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative name -> bytes): nothing changed either."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def fails(capfd, argv, needle: str, keep: Path | None = None,
          snapshot: Callable[[Path], object] = listing) -> str:
    """Run the CLI on ``argv``; assert exit 2, one stderr line holding ``needle`` and no
    traceback, and ``keep`` the same by ``snapshot`` afterwards. Returns the line."""
    before = snapshot(keep) if keep is not None else None
    capfd.readouterr()
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as e:  # argparse's own errors
        code = e.code
    err = capfd.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, (code, err[-2000:])
    assert len(lines) == 1 and "Traceback" not in err, err[-2000:]
    assert needle in lines[0], lines[0]
    if keep is not None:
        assert snapshot(keep) == before, f"{keep} changed"
    return lines[0]
