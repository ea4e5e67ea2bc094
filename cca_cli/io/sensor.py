"""What the values in a capture set's image files mean: containers, bit depths, channels.

A lab camera often writes N-bit data (10, 12, 14 bits) into 16-bit files,
shifted left so that the most significant bits line up (MSB-aligned: a
12-bit code c is stored as ``c << 4``, full scale 65520), or not shifted
(LSB-aligned: full scale 4095). Colour files need a rule saying which
channel holds the signal, and single-channel Bayer mosaics a rule saying
which colour sites to keep. This module reads that meaning from the
manifest's ``sensor`` section and, where the manifest is silent, from the
values themselves, and refuses sets that contradict themselves:

* every capture, dark and flat frame must have the same container, declared
  bit depth and channel layout (one 8-bit PNG among 16-bit TIFFs would be
  256x too dark); calibration (board) views, which are only searched for
  corners, may have their own depth (:func:`board_decodings`);
* colour frames need ``sensor.channel`` and mosaics ``sensor.bayer``;
* a stated bit depth, alignment or white level must agree with the values.

Decoded values are *counts*: N-bit codes when ``sensor.bit_depth`` is given
(the black and white levels are then in codes too), otherwise the stored
values (levels in stored units). Each refusal is one line naming the file
and the fix.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np

from cca_cli.errors import ConfigError, InputError
from cca_cli.io.images import StoredImage

__all__ = ["SensorRule", "FrameValues", "Decoding", "frame_values", "decide_decoding", "same_depth", "board_decodings"]

_BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")


@dataclass(frozen=True)
class SensorRule:
    """How the manifest says the stored values are to be read.

    Attributes
    ----------
    bit_depth : int or None
        Significant bits of the data (N).
    container_bits : int or None
        Bits of the integer type the files use (8, 16, 32).
    alignment : {"msb", "lsb"} or None
        N-bit codes shifted to the top of the container (msb) or not (lsb);
        None: detected from the values.
    channel : int, str or None
        Channel of colour files to use (index or name such as ``G``).
    bayer_pattern : str or None
        Colour filter layout of single-channel mosaics (``RGGB`` …).
    bayer_colour : str or None
        Sites of the mosaic to keep (``R``, ``G`` or ``B``; the two green
        sites of a 2x2 cell are averaged).
    source : str
        The manifest, named in errors about these keys.
    """

    bit_depth: int | None = None
    container_bits: int | None = None
    alignment: str | None = None
    channel: int | str | None = None
    bayer_pattern: str | None = None
    bayer_colour: str | None = None
    source: str = "manifest"

    @property
    def pixel_binning(self) -> int:
        """Sensor pixels per output pixel along each axis (2 for a Bayer rule, else 1)."""
        return 2 if self.bayer_pattern else 1


@dataclass(frozen=True)
class FrameValues:
    """One file's single-channel stored values and the facts the decoding is decided from."""

    values: np.ndarray              # float32 (H, W), stored units
    path: str
    container_bits: int | None
    significant_bits: int | None
    channels: int
    max_value: float
    low_bits: int                   # bitwise OR of every integer value (0 for float data)
    distinct: int = 0               # number of distinct integer values (0 for float data)
    at_max: int = 0                 # pixels at max_value


#: Pixels at one value below the container's full scale that say a sensor of fewer bits clipped there.
_CLIPPED_PIXELS = 10


def _clipped_below_full_scale(frames: list[FrameValues], container: int, top: float) -> list[str]:
    """A note when many pixels sit at exactly ``2**b − 1`` (b < the container's bits) and none above: a ``b``-bit
    sensor clipping there, whose clipped pixels would otherwise be fitted as recorded."""
    bits = next((b for b in range(8, container) if top == 2**b - 1), None)
    if bits is None:
        return []
    at_top = [(f.at_max, f.path) for f in frames if f.max_value == top]
    count, path = max(at_top)
    if count < _CLIPPED_PIXELS:
        return []
    return [f"{count} pixels of {os.path.basename(path)} sit at exactly {top:g} = 2^{bits} − 1, and no frame's go "
            f"above: {bits}-bit data clipping there? state sensor.bit_depth: {bits} (or sensor.white_level: {top:g}) "
            "so that they count as clipped"]


@dataclass(frozen=True)
class Decoding:
    """How stored values become counts, decided for a whole capture set.

    Attributes
    ----------
    shift : int
        Stored values are divided by ``2**shift`` (an MSB-aligned container
        stated as N-bit data).
    code_bits : int or None
        Bits of the counts (None for float data).
    full_scale : float or None
        Largest value the counts can take (``2**code_bits - 1``, or the
        largest MSB-aligned value in stored units); None for float data.
    level_units : str
        ``codes`` (N-bit codes: ``sensor.bit_depth`` stated) or ``stored``.
    notes : list of str
        What was detected from the values (shown once to the user).
    """

    shift: int
    code_bits: int | None
    full_scale: float | None
    level_units: str
    notes: list[str] = field(default_factory=list)


def _bits_text(bits: int | None) -> str:
    return "float" if bits is None else f"{bits}-bit"


def _select_channel(stored: StoredImage, rule: SensorRule) -> np.ndarray:
    data = stored.data
    colour = stored.colour_channels
    if rule.bayer_pattern is not None:
        if data.shape[-1] != 1:
            raise InputError(f"{stored.path}: has {data.shape[-1]} channels but sensor.bayer describes a "
                             "single-channel mosaic; remove sensor.bayer or give sensor.channel")
        return _bayer_sites(data[..., 0], rule, stored.path)
    if rule.channel is None:
        if len(colour) > 1:
            names = ", ".join(stored.channel_names[c] for c in colour)
            raise InputError(f"{stored.path}: is a colour image ({names}); set sensor.channel in {rule.source} "
                             f"(a channel name or index 0..{data.shape[-1] - 1}) or save grey frames")
        return data[..., colour[0]]
    if isinstance(rule.channel, str):
        names = [n.upper() for n in stored.channel_names]
        if rule.channel.upper() not in names:
            if len(colour) == 1:
                return data[..., colour[0]]
            raise InputError(f"{stored.path}: has no channel {rule.channel!r} (channels: "
                             f"{', '.join(stored.channel_names)}); fix sensor.channel in {rule.source}")
        return data[..., names.index(rule.channel.upper())]
    if not 0 <= rule.channel < data.shape[-1]:
        raise InputError(f"{stored.path}: has {data.shape[-1]} channel(s), sensor.channel is {rule.channel}; "
                         f"use 0..{data.shape[-1] - 1} in {rule.source}")
    return data[..., rule.channel]


def _bayer_sites(mosaic: np.ndarray, rule: SensorRule, path: str) -> np.ndarray:
    h, w = mosaic.shape
    if h % 2 or w % 2:
        raise InputError(f"{path}: a Bayer mosaic must have an even size, got {w}x{h} px; crop the frames")
    sites = [(i // 2, i % 2) for i, c in enumerate(rule.bayer_pattern) if c == rule.bayer_colour]
    planes = [mosaic[dy::2, dx::2] for dy, dx in sites]
    if len(planes) == 1:
        return planes[0]
    # The two green sites of a cell: their mean keeps integer codes exact in float32 (half-integers).
    return (planes[0].astype(np.float64) + planes[1]) / 2.0


def frame_values(stored: StoredImage, rule: SensorRule) -> FrameValues:
    """Pick the signal channel (or mosaic sites) of one file and record its value facts.

    Raises
    ------
    InputError
        A colour file without a channel rule, a missing channel, a mosaic of
        odd size, or NaN/infinite float values; one line naming the file.
    """
    plane = _select_channel(stored, rule)
    if stored.container_bits is None:
        values = np.asarray(plane, np.float32)
        bad = ~np.isfinite(values)
        if bad.any():
            raise InputError(f"{stored.path}: {int(bad.sum())} pixel(s) are NaN or infinite; "
                             "fix or mask them and re-export the image")
        low = 0
    else:
        integer = np.asarray(stored.data[..., stored.colour_channels])
        low = int(np.bitwise_or.reduce(integer.ravel())) if integer.size else 0
        values = np.asarray(plane, np.float32)
    distinct = 0
    if stored.container_bits is not None and stored.container_bits <= 16 and values.size:
        distinct = int(np.count_nonzero(np.bincount(np.asarray(stored.data, np.int64).ravel())))
    top = float(values.max()) if values.size else 0.0
    return FrameValues(values=values, path=stored.path, container_bits=stored.container_bits,
                       significant_bits=stored.significant_bits, channels=stored.data.shape[-1],
                       max_value=top, low_bits=low, distinct=distinct,
                       at_max=int(np.count_nonzero(values == top)) if values.size else 0)


def _trailing_zero_bits(value: int, limit: int) -> int:
    if value == 0:
        return 0
    count = 0
    while count < limit and not (value >> count) & 1:
        count += 1
    return count


def decide_decoding(frames: list[FrameValues], rule: SensorRule, *, white_level: float | None) -> Decoding:
    """Decide how a capture set's stored values become counts, or refuse the set.

    Parameters
    ----------
    frames : list of FrameValues
        Every file of the set (coherent, calibration, dark and flat frames).
    rule : SensorRule
        What the manifest states.
    white_level : float or None
        ``sensor.white_level`` as stated (codes with a bit depth, else stored units).

    Returns
    -------
    Decoding

    Raises
    ------
    InputError
        Mixed containers, bit depths or channel layouts; values a stated bit
        depth, alignment or white level contradicts.
    ConfigError
        Contradictory sensor keys (a bit depth above the container …).
    """
    first = frames[0]
    for frame in frames[1:]:
        if (frame.container_bits, frame.significant_bits) != (first.container_bits, first.significant_bits):
            raise InputError(
                f"{frame.path}: is {_bits_text(frame.significant_bits)} data but {first.path} is "
                f"{_bits_text(first.significant_bits)}; every frame of a capture set must have the same bit depth: "
                "re-export this file like the others")
        if frame.channels != first.channels:
            raise InputError(f"{frame.path}: has {frame.channels} channel(s) but {first.path} has {first.channels}; "
                             "re-export every frame with the same channels")
    container, significant = first.container_bits, first.significant_bits
    notes: list[str] = []
    if container is None:
        if rule.bit_depth is not None or rule.container_bits is not None or rule.alignment is not None:
            raise ConfigError(f"{rule.source}: sensor.bit_depth/container_bits/alignment describe integer files but "
                              f"{first.path} holds float values; remove those keys")
        return _checked(frames, Decoding(0, None, None, "stored"), white_level, rule)
    if rule.container_bits is not None and rule.container_bits != container:
        raise InputError(f"{first.path}: is a {container}-bit file but sensor.container_bits is "
                         f"{rule.container_bits} ({rule.source}); fix sensor.container_bits")
    if significant < container:  # the file declares its bit depth (packed n-bit TIFF): values are codes
        if rule.bit_depth is not None and rule.bit_depth != significant:
            raise InputError(f"{first.path}: declares {significant}-bit data but sensor.bit_depth is "
                             f"{rule.bit_depth} ({rule.source}); fix sensor.bit_depth")
        return _checked(frames, Decoding(0, significant, float(2**significant - 1), "codes"), white_level, rule)
    low_bits = 0
    for frame in frames:
        low_bits |= frame.low_bits
    top = max(frame.max_value for frame in frames)
    # Enough distinct values that empty low bits in all of them are no accident.
    varied = sum(frame.distinct for frame in frames) >= 16
    n = rule.bit_depth
    if n is None:
        zeros = _trailing_zero_bits(low_bits, container - 1)
        if zeros >= 2 and low_bits and varied:
            bits = container - zeros
            notes.append(f"every value is a multiple of {2**zeros}: reading {bits}-bit data MSB-aligned in "
                         f"{container}-bit files, levels in stored units (full scale {(2**bits - 1) << zeros}); "
                         f"state sensor.bit_depth: {bits} to work in {bits}-bit codes")
            return _checked(frames, Decoding(0, container, float((2**bits - 1) << zeros), "stored", notes),
                            white_level, rule)
        if white_level is None:
            notes += _clipped_below_full_scale(frames, container, top)
        return _checked(frames, Decoding(0, container, float(2**container - 1), "stored", notes), white_level, rule)
    if n > container:
        raise ConfigError(f"{rule.source}: sensor.bit_depth {n} does not fit the {container}-bit files "
                          f"({first.path}); fix sensor.bit_depth")
    full = float(2**n - 1)
    shift = container - n
    zeros = _trailing_zero_bits(low_bits, container - 1)
    if zeros > shift and low_bits and varied:   # emptier low bits than n-bit codes leave: fewer bits, stated wrong?
        notes.append(f"every value is a multiple of {2**zeros}, as {container - zeros}-bit data MSB-aligned in "
                     f"{container}-bit files would be, but sensor.bit_depth says {n}: check sensor.bit_depth "
                     "(the black and white levels are read in its codes)")
    if shift == 0:
        return _checked(frames, Decoding(0, n, full, "codes", notes), white_level, rule)
    alignment = rule.alignment
    if alignment is None:
        if top > full and low_bits % (1 << shift) == 0 and varied:
            alignment = "msb"
            notes.append(f"{n}-bit data in {container}-bit files: the values are multiples of {1 << shift}, "
                         f"so they are read as MSB-aligned (divided by {1 << shift}); state sensor.alignment: msb "
                         "to make this explicit")
        elif top <= full:
            alignment = "lsb"
            if top > 0 and low_bits % (1 << shift) == 0:
                notes.append(f"{n}-bit data in {container}-bit files: every value fits {n} bits, so they are read "
                             "unshifted (LSB-aligned); state sensor.alignment to make this explicit")
        else:
            culprit = next(f for f in frames if f.max_value > full)
            raise InputError(f"{culprit.path}: holds values up to {culprit.max_value:g}, above the largest "
                             f"{n}-bit code {full:g}, and they are not multiples of {1 << shift} (MSB-aligned "
                             f"{n}-bit data); the data are not {n}-bit: fix sensor.bit_depth in {rule.source}")
    if alignment == "msb":
        culprit = next((f for f in frames if f.low_bits % (1 << shift)), None)
        if culprit is not None:
            raise InputError(f"{culprit.path}: has values that are not multiples of {1 << shift}, so they are not "
                             f"{n}-bit codes MSB-aligned in {container} bits; fix sensor.bit_depth or "
                             f"sensor.alignment in {rule.source}")
        return _checked(frames, Decoding(shift, n, full, "codes", notes), white_level, rule)
    culprit = next((f for f in frames if f.max_value > full), None)
    if culprit is not None:
        raise InputError(f"{culprit.path}: holds values up to {culprit.max_value:g}, above the largest {n}-bit code "
                         f"{full:g}; the data look MSB-aligned: set sensor.alignment: msb in {rule.source}")
    return _checked(frames, Decoding(0, n, full, "codes", notes), white_level, rule)


def same_depth(frame: FrameValues, reference: FrameValues) -> bool:
    """Whether two files hold values of one kind: the same container and declared bit depth."""
    return (frame.container_bits, frame.significant_bits) == (reference.container_bits, reference.significant_bits)


def board_decodings(boards: list[FrameValues], stated: list[int | None], rule: SensorRule) -> list[Decoding]:
    """Decode calibration views at another bit depth than the captures, each depth on its own values.

    Board views only serve to find the board's corners, so a view taken in
    another camera mode (an 8-bit photo beside 12-bit captures) is read at its
    own depth: the bit depth its row states applies, and the channel rules,
    but not the sensor's container, alignment or white level (they describe
    the captures).

    Parameters
    ----------
    boards : list of FrameValues
        The views at another depth than the captures.
    stated : list of int or None
        The bit depth each view's row states.
    rule : SensorRule
        The manifest's rule (for the channel, mosaic and the manifest's name).

    Returns
    -------
    list of Decoding
        One per view; views of one container, declared and stated depth share one decision.

    Raises
    ------
    InputError
        A stated bit depth the view's file or values contradict.
    """
    own = replace(rule, container_bits=None, alignment=None)
    groups: dict[tuple, list[int]] = {}
    for i, (frame, bits) in enumerate(zip(boards, stated)):
        if bits is not None and frame.container_bits is not None and bits > frame.container_bits:
            raise InputError(f"{frame.path}: is a {frame.container_bits}-bit file but its row states bit depth "
                             f"{bits}; state the view's own bit depth in its row, or none ({rule.source}; calibration "
                             "views may have another depth than the captures)")
        groups.setdefault((frame.container_bits, frame.significant_bits, bits), []).append(i)
    out: list[Decoding | None] = [None] * len(boards)
    for (_, _, bits), members in groups.items():
        decoding = decide_decoding([boards[i] for i in members], replace(own, bit_depth=bits), white_level=None)
        for i in members:
            out[i] = replace(decoding, notes=[])
    return out


def _checked(frames: list[FrameValues], decoding: Decoding, white_level: float | None,
             rule: SensorRule) -> Decoding:
    """Refuse a white level above full scale or below values the data hold."""
    if white_level is None:
        return decoding
    units = "codes" if decoding.level_units == "codes" else "stored units"
    if decoding.full_scale is not None and white_level > decoding.full_scale:
        what = (f"the largest {decoding.code_bits}-bit code" if decoding.level_units == "codes"
                else f"the largest value these {frames[0].container_bits}-bit files hold")
        raise InputError(f"{frames[0].path}: sensor.white_level {white_level:g} is above {decoding.full_scale:g}, "
                         f"{what}; give the white level in {units} in {rule.source}")
    scale = float(2**decoding.shift)
    culprit = max(frames, key=lambda f: f.max_value)
    if culprit.max_value / scale > white_level:
        hint = ("give the clipping level in stored units, or state sensor.bit_depth (and alignment) to give it in codes"
                if decoding.level_units == "stored" else "check sensor.white_level, bit_depth and alignment")
        raise InputError(f"{culprit.path}: holds values up to {culprit.max_value / scale:g} {units}, above "
                         f"sensor.white_level {white_level:g}: the level is too low or in other units; {hint} "
                         f"({rule.source})")
    return decoding
