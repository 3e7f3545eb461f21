"""An edit run's config tree: the plan, the trainer and how the dataset is read.

``python -m experiments edit`` generates its settings' flags from
:class:`EditRunConfig`; :func:`jaxedit.edit.progressive.run_edit` runs the plan and the
trainer settings it holds.
"""

from __future__ import annotations

import dataclasses

from ..edit.plan import ProEditConfig
from ..edit.trainer import TrainSettings
from ..errors import DataError


@dataclasses.dataclass(frozen=True)
class EditRunConfig:
    """An edit run's settings.

    Attributes:
      plan: the driver's plan (:class:`jaxedit.edit.plan.ProEditConfig`; its mode's
        defaults from :meth:`ProEditConfig.for_mode`).
      train: the editing trainer (:class:`jaxedit.edit.trainer.TrainSettings`).
      downscale: image downscale factor of the dataset.
      test_views: at most this many held-out views in snapshots and metrics (None: all).
    """

    plan: ProEditConfig = ProEditConfig()
    train: TrainSettings = TrainSettings()
    downscale: int = 1
    test_views: int | None = None

    def __post_init__(self):
        if self.downscale < 1:
            raise DataError("downscale", f"must be >= 1, got {self.downscale}")
        if self.test_views is not None and self.test_views < 1:
            raise DataError("test_views", f"must be >= 1, got {self.test_views}")
