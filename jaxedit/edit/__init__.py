"""Instruction editing: editors, difficulty, the subtask scheduler, the ProEdit driver."""

from .editors import Editor, interpolate_embedding

__all__ = ["Editor", "interpolate_embedding"]
