"""Read and write single-channel capture images with OpenImageIO.

Integer images are returned as raw sensor counts (a 16-bit TIFF holding
12-bit data gives values 0..4095), never normalised to 0..1, because the
HDR merge and the noise model work in counts. Float images (EXR, float TIFF)
are returned as stored.
"""

from __future__ import annotations

import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.errors import CcaError, InputError

__all__ = ["RawImage", "StoredImage", "read_image", "read_stored", "to_linear", "saturation_mask", "write_image"]

_log = logging.getLogger(__name__)

_REEXPORT = "re-export it as TIFF/PNG/EXR"
_INT_BITS = {"uint8": 8, "uint16": 16, "uint32": 32, "int8": 8, "int16": 16, "int32": 32}
_WRITE_EXTS = (".tif", ".tiff", ".png", ".exr")


def _oiio():
    """OpenImageIO, imported on first use: reading captures.h5 alone never needs it."""
    import OpenImageIO

    return OpenImageIO


@dataclass(frozen=True)
class RawImage:
    """One image as read from disk.

    Attributes
    ----------
    pixels : numpy.ndarray
        float32 ``(H, W)``; raw counts for integer files, stored values for
        float files.
    bit_depth : int or None
        Significant bits of integer data (8, 16, or the file's
        ``oiio:BitsPerSample`` such as 12 for packed 12-bit TIFF); None for
        float data.
    format : str
        Stored pixel type as OpenImageIO names it (``"uint8"``, ``"uint16"``,
        ``"float"``, ``"half"``...).
    path : str
        The file that was read.
    """

    pixels: np.ndarray
    bit_depth: int | None
    format: str
    path: str

    @property
    def white_level(self) -> float | None:
        """Largest code value of integer data, ``2**bit_depth - 1``; None for float data."""
        return None if self.bit_depth is None else float(2**self.bit_depth - 1)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


@dataclass(frozen=True)
class StoredImage:
    """One image file's values exactly as stored, with what the file says about them.

    Attributes
    ----------
    data : numpy.ndarray
        ``(H, W, C)`` stored values: unsigned/signed integers for integer files
        (packed n-bit data, e.g. a 12-bit TIFF, as n-bit codes), float32 for
        float files.
    container_bits : int or None
        Bits per sample of the integer type that holds the values (8, 16, 32);
        None for float data.
    significant_bits : int or None
        Bits the file declares as significant (``oiio:BitsPerSample``, e.g. 12
        for a packed 12-bit TIFF); equals ``container_bits`` when the file
        declares nothing; None for float data.
    channel_names : tuple of str
        Channel names (``R``, ``G``, ``B``, ``A``, ``Y`` …).
    alpha_channel : int
        Index of the alpha channel, or -1.
    format : str
        Stored pixel type as OpenImageIO names it.
    path : str
        The file that was read.
    """

    data: np.ndarray
    container_bits: int | None
    significant_bits: int | None
    channel_names: tuple[str, ...]
    alpha_channel: int
    format: str
    path: str

    @property
    def colour_channels(self) -> list[int]:
        """Indices of the channels that are not alpha."""
        return [c for c in range(self.data.shape[-1]) if c != self.alpha_channel] or list(range(self.data.shape[-1]))

    @property
    def code_bits(self) -> int | None:
        """Bits of the codes in :attr:`data` (the significant bits; None for float data)."""
        return self.significant_bits


def read_stored(path) -> StoredImage:
    """Read one image file's stored values, all channels, without any conversion.

    Parameters
    ----------
    path : str or os.PathLike
        Image file (TIFF, PNG, EXR, or anything OpenImageIO reads).

    Returns
    -------
    StoredImage

    Raises
    ------
    InputError
        The file is missing, cannot be decoded, or is not a 2-D image; the
        message is one line naming the file.

    Notes
    -----
    OpenImageIO expands packed n-bit integer data (e.g. 12-bit TIFF) to the
    full 16-bit range by bit replication; the codes are shifted back, so
    ``data`` holds the n-bit codes the file stores. Only the first subimage
    of multi-image files is read.
    """
    name = os.fspath(path)
    if not os.path.exists(name) and os.path.islink(name):
        raise InputError(f"{name}: is a symbolic link that leads nowhere (it loops, or what it points to is gone); "
                         "fix the link or give the image file itself")
    if not os.path.exists(name):
        raise InputError(f"{name}: file not found; check the path and the capture folder")
    if os.path.isdir(name):
        raise InputError(f"{name}: is a directory, not an image file; give the image file path")
    oiio = _oiio()
    inp = oiio.ImageInput.open(name)
    if inp is None:
        _log.debug("OpenImageIO could not open %s: %s", name, _one_line(oiio.geterror()))
        raise InputError(f"{name}: cannot read image (not a supported format or corrupt); {_REEXPORT}")
    try:
        spec = inp.spec()
        fmt = str(spec.format)
        nch = int(spec.nchannels)
        try:
            data = inp.read_image(0, 0, 0, nch, spec.format)
        except Exception as exc:  # noqa: BLE001 - any decoder failure is a corrupt file
            _log.debug("OpenImageIO failed to read %s: %s", name, _one_line(exc))
            data = None
        err = inp.geterror() if hasattr(inp, "geterror") else ""
        if data is None or err:
            _log.debug("OpenImageIO error reading %s: %s", name, _one_line(err))
            raise InputError(f"{name}: cannot read image (truncated or corrupt); {_REEXPORT}")
        alpha = int(spec.alpha_channel)
        names = tuple(str(n) for n in spec.channelnames) or tuple(str(c) for c in range(nch))
        bits_attr = spec.getattribute("oiio:BitsPerSample")
    finally:
        inp.close()

    data = np.asarray(data)
    if data.ndim == 2:
        data = data[..., None]
    if data.ndim != 3:
        raise InputError(f"{name}: is a volume or deep image (shape {data.shape}); {_REEXPORT} as a 2-D image")
    container = significant = None
    if fmt in _INT_BITS:
        container = significant = _INT_BITS[fmt]
        if bits_attr is not None and 0 < int(bits_attr) < container:
            significant = int(bits_attr)
            data = np.right_shift(data, container - significant)
    else:
        data = data.astype(np.float32, copy=False)
    return StoredImage(data=np.ascontiguousarray(data), container_bits=container, significant_bits=significant,
                       channel_names=names, alpha_channel=alpha, format=fmt, path=name)


def read_image(path, *, channel: int | None = None) -> RawImage:
    """Read one image file as a single-channel float32 array.

    Parameters
    ----------
    path : str or os.PathLike
        Image file (TIFF, PNG, JPEG, EXR, or anything OpenImageIO reads).
    channel : int or None, optional
        Channel to return. None (default) returns the only channel of a mono
        image, or the mean of the colour channels (alpha excluded) of a
        multi-channel image. Capture frames go through
        :mod:`cca_cli.io.sensor`, which refuses colour frames without a rule.

    Returns
    -------
    RawImage
        Pixels (float32, raw counts for integer data), bit depth, stored
        format and path.

    Raises
    ------
    InputError
        The file is missing, cannot be decoded, has no such channel, or
        holds NaN/infinite values. The message is one line naming the file.

    Notes
    -----
    Packed n-bit integer data (e.g. 12-bit TIFF) come back as their n-bit
    codes (see :func:`read_stored`).
    """
    stored = read_stored(path)
    name = stored.path
    nch = stored.data.shape[-1]
    if channel is not None and not 0 <= channel < nch:
        raise InputError(f"{name}: has {nch} channel(s), channel {channel} requested; use a channel in 0..{nch - 1}")
    if channel is not None:
        mono = stored.data[..., channel].astype(np.float32)
    elif nch == 1:
        mono = stored.data[..., 0].astype(np.float32)
    else:
        mono = stored.data[..., stored.colour_channels].astype(np.float32).mean(axis=-1, dtype=np.float32)
    if stored.container_bits is None:
        bad = ~np.isfinite(mono)
        if bad.any():
            raise InputError(
                f"{name}: {int(bad.sum())} pixel(s) are NaN or infinite; fix or mask them and re-export the image"
            )
    return RawImage(pixels=np.ascontiguousarray(mono, dtype=np.float32), bit_depth=stored.significant_bits,
                    format=stored.format, path=name)


def to_linear(raw, *, black_level: float = 0.0, white_level: float | None = None) -> np.ndarray:
    """Subtract the black level, keeping sensor counts.

    Parameters
    ----------
    raw : RawImage or array_like
        Raw counts.
    black_level : float, optional
        Sensor offset to subtract (counts). Default 0.
    white_level : float or None, optional
        Raw clipping level. When given, values are also clipped at
        ``white_level - black_level``, so every saturated pixel sits exactly
        at the saturation level the HDR merge is given.

    Returns
    -------
    numpy.ndarray
        float32, ``max(raw - black_level, 0)`` (and at most
        ``white_level - black_level``).

    Raises
    ------
    ValueError
        ``white_level`` not above ``black_level``, or non-finite levels.
    """
    pixels = raw.pixels if isinstance(raw, RawImage) else np.asarray(raw)
    if not np.isfinite(black_level):
        raise ValueError(f"black_level {black_level!r} must be finite")
    out = np.asarray(pixels, dtype=np.float32) - np.float32(black_level)
    upper = None
    if white_level is not None:
        if not np.isfinite(white_level) or white_level <= black_level:
            raise ValueError(f"white_level {white_level!r} must be finite and above black_level {black_level!r}")
        upper = np.float32(white_level - black_level)
    return np.clip(out, np.float32(0.0), upper).astype(np.float32, copy=False)


def saturation_mask(raw, white_level: float) -> np.ndarray:
    """Pixels at or above the raw white (clipping) level.

    Parameters
    ----------
    raw : RawImage or array_like
        Raw counts (before black-level subtraction).
    white_level : float
        Raw clipping level in counts.

    Returns
    -------
    numpy.ndarray
        bool mask, True where the pixel is saturated.
    """
    pixels = raw.pixels if isinstance(raw, RawImage) else np.asarray(raw)
    return np.asarray(pixels) >= white_level


def write_image(path, pixels, *, bit_depth: int = 16) -> None:
    """Write a single-channel image atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Output file; the extension picks the format: ``.tif``/``.tiff``,
        ``.png`` or ``.exr``.
    pixels : array_like
        ``(H, W)`` values. For integer output they are raw counts, rounded to
        the nearest integer.
    bit_depth : int, optional
        8 or 16 for unsigned integer TIFF/PNG (values must lie in
        ``0..2**bit_depth-1``), 32 for float32 TIFF. EXR is always written
        as float32 and ignores this option. Default 16.

    Raises
    ------
    ValueError
        Unsupported extension or bit depth, wrong shape, NaN in integer
        output, or values out of the integer range.
    CcaError
        The file could not be written (one-line message naming it).

    Notes
    -----
    The image is written to a hidden temporary file in the target
    directory and moved into place with :func:`os.replace`, so readers never
    see a half-written file.
    """
    name = os.fspath(path)
    ext = Path(name).suffix.lower()
    if ext not in _WRITE_EXTS:
        raise ValueError(f"{name}: unsupported extension {ext!r}; use one of {', '.join(_WRITE_EXTS)}")
    arr = np.asarray(pixels)
    if arr.ndim != 2:
        raise ValueError(f"{name}: pixels have shape {arr.shape}; expected a single-channel (H, W) array")
    if ext == ".exr":
        data, fmt = arr.astype(np.float32), "float"
    elif bit_depth == 32:
        if ext == ".png":
            raise ValueError(f"{name}: PNG cannot hold float data; use bit_depth 8/16 or a .tif/.exr file")
        data, fmt = arr.astype(np.float32), "float"
    elif bit_depth in (8, 16):
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}: pixels contain NaN or infinite values; cannot store them as integers")
        top = 2**bit_depth - 1
        rounded = np.rint(arr.astype(np.float64))
        if rounded.size and (rounded.min() < 0 or rounded.max() > top):
            raise ValueError(
                f"{name}: values span {rounded.min():g}..{rounded.max():g}, outside 0..{top} for {bit_depth}-bit output"
            )
        dtype = np.uint8 if bit_depth == 8 else np.uint16
        data, fmt = rounded.astype(dtype), ("uint8" if bit_depth == 8 else "uint16")
    else:
        raise ValueError(f"bit_depth {bit_depth!r} not supported; use 8, 16 (integer) or 32 (float TIFF)")

    directory = os.path.dirname(os.path.abspath(name))
    try:
        fd, tmp = tempfile.mkstemp(prefix="." + Path(name).stem + ".", suffix=ext, dir=directory)
    except OSError as exc:
        raise CcaError(f"{name}: cannot write image ({exc.strerror}); check the folder exists and is writable") from exc
    os.close(fd)
    try:
        oiio = _oiio()
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise CcaError(f"{name}: cannot write image ({_one_line(oiio.geterror())})")
        height, width = data.shape
        spec = oiio.ImageSpec(width, height, 1, fmt)
        if ext in (".tif", ".tiff"):
            spec.attribute("compression", "zip")
        ok = out.open(tmp, spec) and out.write_image(np.ascontiguousarray(data[..., None]))
        err = out.geterror()
        closed = out.close()
        if not ok or not closed:
            raise CcaError(f"{name}: cannot write image ({_one_line(err) or 'write failed'}); check free disk space")
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; give the usual file mode
        os.replace(tmp, name)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
