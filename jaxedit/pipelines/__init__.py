"""Pipelines: runs with a run directory, the library half of the commands.

:mod:`.reconstruct` (fit a dataset), :mod:`.edit` (the edit command's config tree,
:func:`run_edit`, :func:`edit_files`), :mod:`.presets`, :mod:`.snapshots`,
:mod:`.rundir` (log and checkpoints), :mod:`.report`, :mod:`.cache`. The library
below writes no run directory: it hands records and states to callbacks.
"""

from .edit_run import EditorConfig, EditRunConfig, edit_files, make_editor, run_edit
from .snapshots import select_snapshot

__all__ = ["EditRunConfig", "EditorConfig", "edit_files", "make_editor", "run_edit",
           "select_snapshot"]
