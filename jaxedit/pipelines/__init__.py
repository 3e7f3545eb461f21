"""Pipelines: runs with a run directory, the library half of the commands that write one.

* :mod:`.reconstruct` -- fit a dataset and write its run directory;
* :mod:`.edit` -- the edit command's config tree (:class:`EditRunConfig`, its
  :class:`EditorConfig`), :func:`run_edit`, a whole progressive edit with its run
  directory, and :func:`edit_files`, the edit of a dataset and a scene on disk as the
  ``edit`` command runs it (its editor and difficulty distance made from the config);
* :mod:`.presets` -- the edit methods' whole config trees (proedit, nd, in2n, igs2gs);
* :mod:`.snapshots` -- snapshot folders of scene states and the user's selection;
* :mod:`.rundir` -- a training run's JSONL log and rolling checkpoints;
* :mod:`.report` -- a run directory's self-contained ``report.html``;
* :mod:`.cache` -- prepared inputs.

The library below this package writes no run directory: :func:`jaxedit.train.fit`
and :func:`jaxedit.edit.progressive.run_plan` hand records and states to callbacks.
``experiments/`` is the thin edge above (flags, progress bars, printing).
"""

from .edit import EditorConfig, EditRunConfig, edit_files, make_editor, run_edit
from .snapshots import select_snapshot

__all__ = ["EditRunConfig", "EditorConfig", "edit_files", "make_editor", "run_edit",
           "select_snapshot"]
