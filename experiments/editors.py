"""The 2D editor a command's :class:`jaxedit.pipelines.edit_run.EditorConfig` names.

The library builds its own editors (:func:`jaxedit.pipelines.edit_run.make_editor`); the
simulated editor, the offline test instrument, is the lab's (:mod:`jaxedit_lab.simulated`)
and is built here, in the layer that may import both.
"""

from __future__ import annotations

#: The commands' 2D editors: the lab's simulated one and the library's
#: (:data:`jaxedit.pipelines.edit_run.EDITORS`).
EDITORS = ("simulated", "ip2p", "ip2p-torch")
#: The edit command's editor without ``--editor``: the offline test instrument.
DEFAULT = "simulated"


def make_editor(config):
    """The editor ``config`` describes: the lab's simulated editor or a library one."""
    if config.kind == "simulated":
        from jaxedit_lab.simulated import SimulatedEditor

        return SimulatedEditor()
    from jaxedit.pipelines.edit_run import make_editor as library_editor

    return library_editor(config)
