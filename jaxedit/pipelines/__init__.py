"""Pipelines: runs with a run directory, the library half of the commands that write one.

:mod:`.reconstruct` (fit a dataset and write its run directory), :mod:`.edit` (the
edit command's config tree), :mod:`.cache` (prepared inputs), :mod:`.report` (a run
directory's self-contained ``report.html``). ``experiments/`` is
their thin edge (flags, progress bars, printing). Run-directory writing still inside
lower modules (``train.fit``'s log and checkpoints, ``edit.progressive.run_edit``)
is to move here.
"""
