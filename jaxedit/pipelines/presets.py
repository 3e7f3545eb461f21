"""The edit methods' presets: one registry of whole config trees, as nerfstudio's
``method_configs``. ``python -m experiments edit --preset NAME`` starts from one (the flags
given win over it) and ``--print-config`` prints the tree a run would use.

- ``proedit``: ProEdit (the paper): difficulty-aware subtasks, opacity resets, budgeted
  creation, the loss plateau;
- ``nd``: no decomposition, the paper's ablation: one subtask at r = 1 with ProEdit's machinery;
- ``in2n``: Instruct-NeRF2NeRF on 3DGS: one subtask at r = 1, one view edited every 10 steps
  at t in [0.02, 0.98], classic density control, a fixed number of steps;
- ``igs2gs``: Instruct-GS2GS: as ``in2n``, but every view edited every 2500 of 7500 steps at
  t in [0.70, 0.98] with text guidance 12.5.
"""

from __future__ import annotations

from typing import Callable

from ..edit.plan import ProEditConfig
from ..edit.trainer import EditTrainConfig
from ..errors import DataError
from .edit_run import EditRunConfig


def _mode(mode: str, **plan) -> EditRunConfig:
    """Mode ``mode``'s plan (with ``plan`` changes) and trainer."""
    return EditRunConfig(plan=ProEditConfig.for_mode(mode, **plan),
                         train=EditTrainConfig.for_mode(mode))


#: name -> a function building that method's whole :class:`EditRunConfig`.
PRESETS: dict[str, Callable[[], EditRunConfig]] = {
    "proedit": lambda: _mode("proedit"),
    "nd": lambda: _mode("nd"),
    "in2n": lambda: _mode("in2n"),
    "igs2gs": lambda: _mode("in2n", max_steps=7500, sweep_every=2500,
                            timestep_range=(0.70, 0.98), guidance=(12.5, 1.5)),
}


def preset(name: str) -> EditRunConfig:
    """The whole config tree of method preset ``name``."""
    if name not in PRESETS:
        raise DataError("preset", f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]()
