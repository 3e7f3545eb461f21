"""A test instrument: the simulated editor, counting its encoder calls per prompt."""

from __future__ import annotations

from jaxedit_lab.simulated import SimulatedEditor


class CountingEditor(SimulatedEditor):
    """The simulated editor, counting its encoder calls per prompt (``encoded``)."""

    def __init__(self):
        super().__init__()
        self.encoded = {}

    def encode(self, prompt):
        self.encoded[prompt] = self.encoded.get(prompt, 0) + 1
        return super().encode(prompt)
