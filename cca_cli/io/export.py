"""Export a recovery as an image file: float32 TIFF, 16-bit PNG or NumPy ``.npy``.

The file format follows the output's suffix (or ``format``, with any suffix).
Every image file records the object-plane pixel size:

- **TIFF** (``.tif``, ``.tiff``): float32 values as stored in ``recon.h5``, at
  full resolution, uncompressed (Deflate with the floating-point predictor,
  which OpenImageIO would pick, is unreadable to ``tifffile`` without
  ``imagecodecs`` and to ImageJ); ``XResolution``/``YResolution`` in pixels
  per centimetre (``ResolutionUnit`` cm, which ImageJ reads as its pixel
  size) and an ``ImageDescription`` holding JSON (quantity, units, pixel size).
- **PNG** (``.png``): 16-bit codes ``c`` with ``value = offset + scale · c``;
  ``offset``, ``scale``, the pixel size, quantity and units are PNG text
  chunks (``cca:offset`` …), the pixel size also the ``pHYs`` chunk.
- **NPY** (``.npy``): the float32 array alone (NumPy files hold no metadata).

Files appear atomically: a failed or interrupted export leaves nothing behind,
and an existing file is replaced only with ``force``. Files are read back by
their content, not their suffix.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.errors import CcaError, ConfigError, InputError
from cca_cli.io.h5 import atomic_path, open_input, require
from cca_cli.io.schema import OBJECT, RECON_INTENSITY

__all__ = ["QUANTITIES", "FORMATS", "ExportedImage", "export_format", "file_format", "recon_quantity", "export_image",
           "export_recon", "read_exported"]

#: What can be exported from a recovery.
QUANTITIES = ("amplitude", "intensity", "phase")
#: Output formats by suffix.
FORMATS = {".tif": "tiff", ".tiff": "tiff", ".png": "png", ".npy": "npy"}

_PNG_TOP = 65535
_MAGIC = ((b"\x93NUMPY", "npy"), (b"II*\x00", "tiff"), (b"MM\x00*", "tiff"), (b"II+\x00", "tiff"),
          (b"MM\x00+", "tiff"), (b"\x89PNG\r\n\x1a\n", "png"))


@dataclass(frozen=True)
class ExportedImage:
    """An exported image read back: values in physical units and what the file records about them.

    Attributes
    ----------
    values : ndarray, float32, (H, W)
        The exported quantity (PNG codes already converted back with scale and offset).
    pixel_size_m : float or None
        Object-plane pixel size (m); None for ``.npy`` files.
    quantity : str or None
        ``amplitude``, ``intensity`` or ``phase``; None when the file does not say.
    units : str or None
        Units of ``values``.
    """

    values: np.ndarray
    pixel_size_m: float | None
    quantity: str | None
    units: str | None


def export_format(path: str | Path, format: str | None = None) -> str:
    """The format (``tiff``, ``png`` or ``npy``) of an output path, from its suffix or ``format``.

    Raises
    ------
    ConfigError
        Unknown suffix without ``format``, unknown ``format``, or a suffix that contradicts it.
    """
    path = Path(path)
    by_suffix = FORMATS.get(path.suffix.lower())
    if format is None:
        if by_suffix is None:
            raise ConfigError(f"{path}: unknown image format {path.suffix or '(no suffix)'!r}; name the file "
                              ".tif/.tiff (float32), .png (16-bit) or .npy, or give --format tiff|png|npy "
                              "(format= in Python)")
        return by_suffix
    chosen = format.lower()
    if chosen == "tif":
        chosen = "tiff"
    if chosen not in ("tiff", "png", "npy"):
        raise ConfigError(f"--format {format!r}: choose one of tiff, png, npy")
    if by_suffix is not None and by_suffix != chosen:
        raise ConfigError(f"{path}: the suffix {path.suffix!r} says {by_suffix} but --format is {chosen}; "
                          "make them agree")
    return chosen


def _check_quantity(quantity: str) -> str:
    if quantity not in QUANTITIES:
        raise ConfigError(f"--quantity {quantity!r}: choose one of {', '.join(QUANTITIES)}")
    return quantity


def recon_quantity(recon_path: str | Path, quantity: str = "amplitude") -> tuple[np.ndarray, float, str]:
    """One quantity of a ``recon.h5`` at full resolution.

    Parameters
    ----------
    recon_path : path
        A file written by ``cca reconstruct``.
    quantity : {'amplitude', 'intensity', 'phase'}
        ``|object|``, ``/recon/intensity`` (``|object|²``) or ``angle(object)`` in radians.

    Returns
    -------
    values : ndarray, float32, (M, M), or (H, W) for a region (/recon/region_px)
    pixel_size_m : float
        Object-plane pixel size of the recovery grid (m), the same along both axes.
    units : str
    """
    _check_quantity(quantity)
    with open_input(recon_path, stage="reconstruct") as handle:
        if quantity == "intensity":
            dataset = require(handle, RECON_INTENSITY, ndim=2)
            values = np.asarray(dataset, np.float32)
            units = _text(dataset.attrs.get("units", ""))
        else:
            dataset = require(handle, OBJECT, ndim=2)
            field = np.asarray(dataset, np.complex64)
            values = (np.abs(field) if quantity == "amplitude" else np.angle(field)).astype(np.float32)
            units = _text(dataset.attrs.get("units", "")) if quantity == "amplitude" else "rad"
        attrs = handle["recon"].attrs
        if "pixel_pitch_object_m" in attrs:
            pixel = float(attrs["pixel_pitch_object_m"])
        else:   # /geometry's field is the whole recovery grid, which a region (/recon/region_px) is part of
            grid = int(attrs["hires_size"]) if "hires_size" in attrs else values.shape[-1]
            pixel = float(handle["geometry"].attrs["field_width_m"]) / grid
    return values, pixel, units


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def export_image(image, path: str | Path, *, pixel_size_m: float, quantity: str = "amplitude", units: str = "",
                 format: str | None = None, force: bool = False) -> Path:
    """Write a real 2-D image as float32 TIFF, 16-bit PNG or ``.npy``, with its pixel size.

    Parameters
    ----------
    image : array_like, real, (H, W)
        Values to write (finite).
    path : path
        Output file; its suffix picks the format unless ``format`` is given.
    pixel_size_m : float
        Object-plane pixel size (m), stored in the file's metadata.
    quantity : str, optional
        What the values are (recorded in the metadata).
    units : str, optional
        Units of the values (recorded in the metadata).
    format : {'tiff', 'png', 'npy'}, optional
        Overrides the suffix.
    force : bool, optional
        Replace an existing file.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``force`` is False.
    ConfigError
        Unknown format.
    InputError
        The image is not a finite real 2-D array.

    Examples
    --------
    >>> import numpy as np, tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> image = np.linspace(0, 2, 12, dtype=np.float32).reshape(3, 4)
    >>> path = export_image(image, folder / "ramp.png", pixel_size_m=2e-6, quantity="intensity")
    >>> back = read_exported(path)
    >>> back.pixel_size_m, bool(np.allclose(back.values, image, atol=2 / 65535))
    (2e-06, True)
    """
    path = Path(path)
    kind = export_format(path, format)
    values = np.asarray(image)
    if values.ndim != 2 or np.iscomplexobj(values):
        raise InputError(f"{path}: cannot export an array of shape {values.shape} and dtype {values.dtype}; "
                         "give a real 2-D image")
    values = values.astype(np.float32)
    if not np.isfinite(values).all():
        raise InputError(f"{path}: the image holds NaN or infinite values; they cannot be exported")
    if not (np.isfinite(pixel_size_m) and pixel_size_m > 0):
        raise ConfigError(f"pixel_size_m {pixel_size_m!r}: give the object pixel size in metres (> 0)")
    meta = {"software": "cca", "quantity": quantity, "units": units, "pixel_size_m": float(pixel_size_m)}
    with atomic_path(path, force=force, owned=written_by_export) as tmp:
        if kind == "npy":
            with open(tmp, "wb") as handle:
                np.save(handle, values)
        elif kind == "tiff":
            _write_oiio(tmp, "tiff", values, "float", meta, path)
        else:
            offset = float(min(0.0, values.min()))
            if quantity == "phase":
                offset = float(min(-np.pi, values.min()))
            span = float(values.max()) - offset
            scale = span / _PNG_TOP if span > 0 else 1.0
            codes = np.clip(np.rint((values.astype(np.float64) - offset) / scale), 0, _PNG_TOP).astype(np.uint16)
            meta.update(offset=offset, scale=scale, encoding="value = offset + scale * code")
            _write_oiio(tmp, "png", codes, "uint16", meta, path)
    return path


def _latin1(text: str) -> str:
    """``text`` as a PNG text chunk may hold it (Latin-1): ``√(x)`` / ``√x`` become ``sqrt(x)``."""
    text = re.sub(r"√(\w+)", r"sqrt(\1)", text.replace("√(", "sqrt("))
    return text.encode("latin-1", "backslashreplace").decode("latin-1")


def _write_oiio(tmp: Path, format_name: str, data: np.ndarray, pixel_type: str, meta: dict, path: Path) -> None:
    import OpenImageIO as oiio

    height, width = data.shape
    spec = oiio.ImageSpec(width, height, 1, pixel_type)
    per_cm = 0.01 / meta["pixel_size_m"]
    spec.attribute("XResolution", float(per_cm))
    spec.attribute("YResolution", float(per_cm))
    spec.attribute("ResolutionUnit", "cm")
    spec.attribute("ImageDescription", json.dumps(meta))
    spec.attribute("Software", "cca")
    if format_name == "tiff":
        spec.attribute("compression", "none")
    else:
        spec.attribute("oiio:ColorSpace", "linear")  # codes are linear in the value, not sRGB-encoded
        for key, value in meta.items():
            spec.attribute(f"cca:{key}", _latin1(repr(value) if isinstance(value, float) else str(value)))
    out = oiio.ImageOutput.create(format_name)
    if out is None:
        raise CcaError(f"{path}: cannot write {format_name} ({oiio.geterror().strip()})")
    ok = out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(data[..., None]))
    error = out.geterror()
    closed = out.close()
    if not (ok and closed):
        raise CcaError(f"{path}: cannot write image ({' '.join(error.split()) or 'write failed'}); "
                       "check free disk space and permissions")
    os.chmod(tmp, 0o644)


def export_recon(recon_path: str | Path, path: str | Path, *, quantity: str = "amplitude", format: str | None = None,
                 force: bool = False) -> Path:
    """Export one quantity of a ``recon.h5`` at full resolution (see :func:`export_image`).

    Parameters
    ----------
    recon_path : path
        A file written by ``cca reconstruct``.
    path : path
        Output file (``.tif``/``.tiff``, ``.png`` or ``.npy``).
    quantity : {'amplitude', 'intensity', 'phase'}
    format : {'tiff', 'png', 'npy'}, optional
        Overrides the suffix.
    force : bool
        Replace an existing output.

    Returns
    -------
    Path
    """
    _check_quantity(quantity)
    kind = export_format(path, format)
    from cca_cli.io.h5 import check_output

    check_output(Path(path), force=force, owned=written_by_export, inputs=(recon_path,))
    values, pixel, units = recon_quantity(recon_path, quantity)
    return export_image(values, path, pixel_size_m=pixel, quantity=quantity, units=units, format=kind, force=force)


def file_format(path: str | Path) -> str | None:
    """``tiff``, ``png`` or ``npy`` as the file's first bytes say (whatever its suffix); None for anything else."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(8)
    except OSError:
        return None
    return next((kind for magic, kind in _MAGIC if head.startswith(magic)), None)


def written_by_export(path: Path) -> bool:
    """Whether ``path`` is a TIFF or PNG that :func:`export_image` wrote (its Software tag says cca).

    A ``.npy`` file carries no such mark, so cca never replaces one it finds.
    """
    if not Path(path).is_file() or file_format(path) not in ("tiff", "png"):
        return False
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        oiio.geterror()
        return False
    try:
        return inp.spec().getattribute("Software") == "cca"
    finally:
        inp.close()


def read_exported(path: str | Path) -> ExportedImage:
    """Read a file written by :func:`export_image` back into physical values.

    The format is read from the file's content, so any suffix works (``cca export --format``).

    Raises
    ------
    InputError
        The file is missing or not a readable image.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    if file_format(path) == "npy":
        try:
            values = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: not a NumPy file ({exc})") from None
        return ExportedImage(np.asarray(values, np.float32), None, None, None)
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read image ({' '.join(oiio.geterror().split())})")
    try:
        spec = inp.spec()
        data = inp.read_image(0, 0, 0, 1, spec.format)
        description = spec.getattribute("ImageDescription")
    finally:
        inp.close()
    if data is None:
        raise InputError(f"{path}: cannot read image")
    data = np.asarray(data).reshape(spec.height, spec.width)
    try:
        meta = json.loads(description) if description else {}
    except ValueError:
        meta = {}
    values = data.astype(np.float64)
    if "scale" in meta:
        values = meta["offset"] + meta["scale"] * values
    return ExportedImage(values.astype(np.float32), meta.get("pixel_size_m"), meta.get("quantity"), meta.get("units"))
