"""Reading and writing scenes: nerfstudio datasets, 3DGS .ply files, images."""

from .files import atomic_path, atomic_write_bytes, atomic_write_text

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text"]
