"""Reading and writing images with OpenImageIO.

Images are float32 [H, W, 3] in [0, 1], values as stored (no colour-space
conversion; float files clipped to [0, 1]). Straight alpha (PNG) is composited as
``rgb * a + bg * (1 - a)``, associated alpha (EXR) as ``rgb + bg * (1 - a)``.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from ..errors import DataError
from .files import atomic_path

_JPEG_MAGIC = b"\xff\xd8\xff"
#: EXIF orientation tags that swap the image's width and height.
SWAPPING_ORIENTATIONS = (5, 6, 7, 8)

#: Suffix -> (pixel type written, description). PNG/JPEG are 8-bit, EXR float32,
#: TIFF 16-bit.
WRITE_FORMATS = {".png": "uint8", ".jpg": "uint8", ".jpeg": "uint8", ".exr": "float",
                 ".tif": "uint16", ".tiff": "uint16"}


def read_image(path: str | os.PathLike, *, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Read an image file as float32 RGB in [0, 1].

    Args:
      path: any format OpenImageIO reads (PNG, JPEG, EXR, TIFF, ...), 8/16-bit
        or float.
      background: RGB in [0, 1] that transparent pixels are composited over.
    Returns:
      float32 [H, W, 3] in [0, 1]. Grey images are expanded to RGB; an alpha
      channel is composited over ``background`` and dropped.
    Raises:
      DataError: missing, unreadable or undecodable file, non-finite pixels.
    """
    path = Path(path)
    colour, alpha, straight = _read_rgb_alpha(path)
    if alpha is not None:
        bg = np.asarray(background, np.float32).reshape(1, 1, 3)
        if straight:
            colour = colour * alpha
        colour = colour + (1.0 - alpha) * bg
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


def utf8_name(path: str | os.PathLike) -> str:
    """``path`` as text for OpenImageIO, which takes UTF-8 names only; a name with stray
    bytes is refused (DataError naming its bytes) rather than failing inside the binding."""
    text = os.fspath(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise DataError(repr(os.fsencode(path)), "file name is not valid UTF-8 (the image "
                                                 "reader takes UTF-8 names); rename the file") from None
    return text


def read_image_with_alpha(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """An image and its transparency, not composited.

    Returns:
      (straight (unpremultiplied) RGB float32 [H, W, 3] in [0, 1],
        alpha float32 [H, W] in [0, 1], or None when the file has no alpha channel).
      Fully transparent pixels of an associated-alpha file come back black.
    """
    path = Path(path)
    colour, alpha, straight = _read_rgb_alpha(path)
    if alpha is None:
        return np.clip(colour, 0.0, 1.0).astype(np.float32), None
    if not straight:
        colour = np.where(alpha > 0, colour / np.maximum(alpha, 1e-12), 0.0)
    return np.clip(colour, 0.0, 1.0).astype(np.float32), alpha[..., 0].astype(np.float32)


def image_header(path: str | os.PathLike) -> tuple[int, int, int]:
    """(height, width, channels) of an image file from its header alone, nothing decoded.

    Raises:
      DataError: missing, unreadable file.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "image file not found" if not path.exists() else "not a file")
    utf8_name(path)
    with _c_stderr_held_back():
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise DataError(path, f"cannot open image ({_oiio_error()})")
        try:
            spec = inp.spec()
            return int(spec.height), int(spec.width), int(spec.nchannels)
        finally:
            inp.close()


def _is_jpeg(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(3) == _JPEG_MAGIC
    except OSError as e:
        raise DataError(path, f"cannot read file ({e.strerror or e})") from None


def photo_header(path: str | os.PathLike) -> tuple[int, int, int, bool]:
    """(stored height, stored width, EXIF orientation 1-8, 8-bit) of an image, nothing decoded.

    Orientation is 1 when the file has none; ``8-bit`` is True only for opaque 8-bit
    integer pixels (alpha compositing falls between the 8-bit levels).

    Raises:
      DataError: missing, unreadable file.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "image file not found" if not path.exists() else "not a file")
    if _is_jpeg(path):
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(path) as im:
                w, h = im.size
                tag = im.getexif().get(0x0112, 1)
        except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as e:
            raise DataError(path, f"cannot open image ({' '.join(str(e).split()) or 'corrupt'})"
                            ) from None
        return h, w, int(tag) if tag in range(1, 9) else 1, True
    utf8_name(path)
    with _c_stderr_held_back():
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise DataError(path, f"cannot open image ({_oiio_error()})")
        try:
            spec = inp.spec()
            tag = spec.get_int_attribute("Orientation", 1)
            eight = spec.format.basetype in (oiio.UINT8, oiio.INT8) and spec.nchannels in (1, 3)
            return (int(spec.height), int(spec.width), tag if tag in range(1, 9) else 1,
                    bool(eight))
        finally:
            inp.close()


def orient(image: np.ndarray, orientation: int) -> np.ndarray:
    """``image`` [H, W, ...] turned upright by its EXIF ``orientation`` (1-8, as Pillow's
    ``ImageOps.exif_transpose``): [W, H, ...] for 5-8."""
    ops = {1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1],
           4: lambda a: a[::-1], 5: lambda a: a.swapaxes(0, 1),
           6: lambda a: a[::-1].swapaxes(0, 1), 7: lambda a: a[::-1, ::-1].swapaxes(0, 1),
           8: lambda a: a[:, ::-1].swapaxes(0, 1)}
    if orientation not in ops:
        raise DataError("orientation", f"must be an EXIF orientation 1-8, got {orientation!r}")
    return ops[orientation](image)


def area_average(image: np.ndarray, factor: int) -> np.ndarray:
    """float32 [H // f, W // f, C]: the mean of each f x f block of ``image`` [H, W, C]
    (the right and bottom remainder cropped); ``factor`` 1 returns it as float32."""
    image = np.asarray(image)
    h, w = image.shape[0] // factor, image.shape[1] // factor
    if factor == 1:
        return image.astype(np.float32, copy=False)
    block = image[:h * factor, :w * factor].astype(np.float32)
    return block.reshape(h, factor, w, factor, -1).mean(axis=(1, 3), dtype=np.float32)


def _jpeg_scale(factor: int, width: int, height: int, orientation: int) -> int:
    """The DCT scale (1, 2, 4, 8) to decode at: the largest dividing ``factor``; 1 when
    re-orientation would move a partial last block to the top or left."""
    scale = next(s for s in (8, 4, 2, 1) if factor % s == 0)
    if orientation != 1 and (width % scale or height % scale):
        return 1
    return scale


def _decode_jpeg(path: Path, factor: int, orientation: int) -> np.ndarray:
    """(uint8 [ceil(H / s), ceil(W / s), 3] decoded at scale 1/s, s dividing ``factor``;
    s; the stored (H, W))."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
            scale = _jpeg_scale(factor, w, h, orientation)
            if scale > 1:
                im.draft("RGB", (max(1, w // scale), max(1, h // scale)))
            im.load()
            # the scale the decoder chose (Pillow may pick a smaller one than asked)
            got = next((g for g in (8, 4, 2, 1)
                        if im.size == (-(-w // g), -(-h // g))), 0)
            pixels = np.asarray(im.convert("RGB") if im.mode != "RGB" else im)
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as e:
        raise DataError(path, f"cannot decode image ({' '.join(str(e).split()) or 'corrupt'})"
                        ) from None
    if not got or factor % got or pixels.shape[:2] != (-(-h // got), -(-w // got)):
        raise DataError(path, f"JPEG decoder returned {pixels.shape[1]}x{pixels.shape[0]} at "
                              f"scale 1/{got}; expected a scale dividing {factor}")
    return pixels, got, (h, w)


def read_photo(path: str | os.PathLike, factor: int = 1, *, orientation: int = 1,
               background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """A photo at 1/``factor`` of its size: float32 [H // f, W // f, 3] in [0, 1].

    The area average of :func:`read_image`'s pixels, turned upright by :func:`orient`
    first so blocks line up. JPEGs are decoded at reduced size by DCT scaling (Pillow's
    ``draft``, exact up to the codec's rounding), so the full-size pixels are never held.

    Args:
      path: an image file.
      factor: integer downscale >= 1.
      orientation: EXIF orientation to apply (1: as stored; :func:`photo_header`).
      background: RGB that transparent pixels are composited over.
    Raises:
      DataError: unreadable, truncated or undecodable file.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "image file not found" if not path.exists() else "not a file")
    if _is_jpeg(path):
        pixels, scale, (h, w) = _decode_jpeg(path, factor, orientation)
        if orientation in SWAPPING_ORIENTATIONS:
            h, w = w, h
        # The last decoded row/column may cover a partial block: crop to whole target pixels.
        out = area_average(orient(pixels, orientation), factor // scale)[:h // factor, :w // factor]
        return out / np.float32(255.0)
    return area_average(orient(read_image(path, background=background), orientation), factor)


def _read_rgb_alpha(path: Path) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """(colour float32 [H, W, 3], alpha [H, W, 1] in [0, 1] or None, alpha is straight)."""
    if not path.is_file():
        raise DataError(path, "image file not found" if not path.exists() else "not a file")
    utf8_name(path)
    # Ask for unassociated alpha as stored: compositing in float avoids the 8-bit
    # rounding of OpenImageIO's premultiply.
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    with _c_stderr_held_back():
        inp = oiio.ImageInput.open(str(path), config)
        if inp is None:
            raise DataError(path, f"cannot open image ({_oiio_error()})")
        try:
            spec = inp.spec()
            straight = spec.get_int_attribute("oiio:UnassociatedAlpha", 0) == 1
            pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
            if pixels is None or inp.has_error:
                raise DataError(path, f"cannot decode image ({_oiio_error(inp)})")
        finally:
            inp.close()
    pixels = np.asarray(pixels, np.float32)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if pixels.ndim != 3 or pixels.shape[0] != spec.height or pixels.shape[1] != spec.width:
        raise DataError(path, f"decoded pixel array has unexpected shape {list(pixels.shape)}")
    if not np.isfinite(pixels).all():
        raise DataError(path, "image has non-finite (NaN or inf) pixel values")
    nch = pixels.shape[2]
    alpha_channel = spec.alpha_channel
    if alpha_channel < 0 and nch in (2, 4):
        alpha_channel = nch - 1  # grey+alpha / RGBA without an explicit alpha tag
    colour_idx = [i for i in range(nch) if i != alpha_channel]
    if not colour_idx:
        raise DataError(path, "image has only an alpha channel")
    colour = pixels[:, :, colour_idx[:3]]
    if colour.shape[2] == 1:
        colour = np.repeat(colour, 3, axis=2)
    elif colour.shape[2] == 2:
        raise DataError(path, "image has two colour channels; expected grey or RGB")
    alpha = None
    if alpha_channel >= 0:
        alpha = np.clip(pixels[:, :, alpha_channel:alpha_channel + 1], 0.0, 1.0)
    return colour, alpha, straight


@contextlib.contextmanager
def _c_stderr_held_back():
    """Hold back what C libraries print on fd 2 (libpng's error line, already in our
    DataError's text): dropped when the block raises, passed on otherwise."""
    fd = 2  # C's stderr, whatever Python's sys.stderr is at the moment
    with tempfile.TemporaryFile() as held:
        sys.stderr.flush()
        saved = os.dup(fd)
        os.dup2(held.fileno(), fd)
        ok = False
        try:
            yield
            ok = True
        finally:
            os.dup2(saved, fd)
            os.close(saved)
            if ok:
                held.seek(0)
                text = held.read()
                if text:
                    os.write(fd, text)


def write_image(path: str | os.PathLike, image, *, metadata: dict | None = None) -> Path:
    """Write an image atomically; the format comes from the suffix.

    Args:
      path: ``.png`` / ``.jpg`` / ``.jpeg`` (8-bit), ``.tif`` (16-bit) or
        ``.exr`` (float32, values kept as they are).
      image: float [H, W, 3], [H, W, 4] (straight alpha) or [H, W]; values in
        [0, 1] (clipped for the integer formats, rounded to nearest).
      metadata: OpenImageIO attributes to store, e.g. ``{"Exif:FocalLengthIn35mmFilm": 50}``.
    Returns the path written.
    """
    path = Path(path)
    utf8_name(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_FORMATS:
        raise DataError(path, f"unsupported image suffix {suffix!r}; use one of "
                              f"{', '.join(sorted(WRITE_FORMATS))}")
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in (1, 3, 4) or 0 in image.shape:
        raise DataError(path, f"image to write must be [H, W], [H, W, 3] or [H, W, 4], "
                              f"got {list(image.shape)}")
    image = image.astype(np.float32)
    if not np.isfinite(image).all():
        raise DataError(path, "image to write has non-finite (NaN or inf) values")
    if suffix in (".jpg", ".jpeg") and image.shape[2] == 4:
        image = image[:, :, :3]  # JPEG has no alpha
    kind = WRITE_FORMATS[suffix]
    if kind == "float" and image.shape[2] == 4:
        # EXR stores associated (premultiplied) alpha.
        image = np.concatenate([image[:, :, :3] * image[:, :, 3:], image[:, :, 3:]], axis=2)
    if kind == "uint8":
        data = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
        td = oiio.UINT8
    elif kind == "uint16":
        data = np.round(np.clip(image, 0.0, 1.0) * 65535.0).astype(np.uint16)
        td = oiio.UINT16
    else:
        data, td = image, oiio.FLOAT
    # OpenImageIO refuses strided buffers: make the pixels C-ordered once.
    data = np.ascontiguousarray(data)
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, td)
    if c == 4:
        spec.alpha_channel = 3
        # Our RGBA is straight alpha: say so, so PNG skips an unpremultiply round trip.
        spec.attribute("oiio:UnassociatedAlpha", 1)
    if suffix in (".jpg", ".jpeg"):
        spec.attribute("Compression", "jpeg:95")
    for key, value in (metadata or {}).items():
        spec.attribute(key, value)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise DataError(path, f"cannot create image writer ({_oiio_error()})")
        try:
            if not out.open(str(tmp), spec):
                raise DataError(path, f"cannot open image for writing ({_oiio_error(out)})")
            if not out.write_image(data):
                raise DataError(path, f"cannot write image ({_oiio_error(out)})")
        finally:
            out.close()
    return path


def _oiio_error(obj=None) -> str:
    msg = ""
    if obj is not None:
        msg = obj.geterror() if hasattr(obj, "geterror") else ""
    msg = msg or oiio.geterror()
    return " ".join(msg.split()) or "unknown error"
