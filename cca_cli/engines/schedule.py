"""Visiting order of a sequential engine: centre-out, in groups threads can update at once.

A sequential engine updates the spectrum one batch of captures at a time, and
each batch reads what the previous one wrote. Two batches may still run at the
same time when their pupil boxes cover disjoint parts of the spectrum: then
running them together gives exactly the result of running one after the
other. :func:`build_schedule` splits the captures by a row of the spectrum
into those whose boxes lie wholly above it, wholly below it, and the seam that
straddles it; the seam is split likewise by a column. The pass then runs in
phases: the core (the seam of the seam, around DC), the left and right arms
side by side, and the upper and lower halves side by side, each group
centre-out. Only the core needs threads to share batches.

For more threads the split goes deeper (``lanes`` 4, 8): each half is split
again by a line across the other axis, and an arm (whose boxes all straddle
the first line) by another line along its own, so a phase holds up to
``lanes`` groups that never touch. Two lanes give the schedule above, so one
and two threads visit the captures in the same order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Phase", "Schedule", "split_disjoint", "shell_sizes", "build_schedule"]

#: Cost of a seam capture relative to one in a side-by-side group (the seam's batches are shared by two threads).
_SEAM_COST = 0.5


@dataclass(frozen=True)
class Phase:
    """Batches of one phase, one sequence per lane.

    Attributes
    ----------
    lanes : tuple of tuple of slice
        Batches as slices of the schedule's order. Boxes of different lanes never overlap,
        so lanes may run concurrently; within a lane batches run in turn.
    """

    lanes: tuple[tuple[slice, ...], ...]


@dataclass(frozen=True)
class Schedule:
    """Captures in visiting order and the phases that visit them.

    Attributes
    ----------
    order : ndarray, int64, (K,)
        Capture indices in visiting order; batches are contiguous slices of it.
    phases : tuple of Phase
    """

    order: np.ndarray
    phases: tuple[Phase, ...]

    @property
    def batches(self) -> list[slice]:
        """Every batch, in an order equivalent to the concurrent one (lane by lane)."""
        return [batch for phase in self.phases for lane in phase.lanes for batch in lane]


def split_disjoint(starts: np.ndarray, size: int, members: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split captures by a line into boxes wholly before it, wholly after it, and the seam across it.

    Parameters
    ----------
    starts : ndarray, int, (K,)
        First row (or column) of every capture's box.
    size : int
        Box side length.
    members : ndarray, int, (n,)
        The captures to split (their order is kept in each part).

    Returns
    -------
    before, after, seam : ndarray, int
        The line is chosen to minimise ``max(len(before), len(after)) + len(seam) / 2``.
    """
    first = starts[members]
    if first.size == 0:
        return members[:0], members[:0], members
    lines = np.unique(np.concatenate([first, first + size]))   # every line worth trying, in increasing order
    n_before = np.searchsorted(np.sort(first + size), lines, side="right")   # boxes ending at or before it
    n_after = first.size - np.searchsorted(np.sort(first), lines, side="left")   # boxes starting at or after it
    cost = np.maximum(n_before, n_after) + _SEAM_COST * (members.size - n_before - n_after)
    line = lines[int(np.argmin(cost))]   # the first line of least cost
    before, after = first + size <= line, first >= line
    return members[before], members[after], members[~(before | after)]


def _full_batches(count: int, batch: int) -> list[slice]:
    """``range(count)`` in slices of ``batch`` items, the last one shorter."""
    return [slice(start, min(start + batch, count)) for start in range(0, count, batch)]


def shell_sizes(count: int, batch: int) -> list[int]:
    """Captures per shell, growing away from DC: 2, 2, 4, 4, 8, 8, … batches, covering ``count``."""
    sizes, doubling = [], 0
    while sum(sizes) < count:
        sizes.append((2 << (doubling // 2)) * batch)
        doubling += 1
    return sizes


def build_schedule(box_origins: np.ndarray, box_size: int, distances: np.ndarray, batch: int,
                   shells: list[int] | None = None, lanes: int = 2) -> Schedule:
    """Centre-out visiting order of captures, split into phases of non-overlapping lanes.

    Parameters
    ----------
    box_origins : ndarray, int, (K, 2)
        Top-left corner ``[row, column]`` of every capture's pupil box in the spectrum.
    box_size : int
    distances : ndarray, float, (K,)
        Distance of each pupil centre from DC; smaller is visited first.
    batch : int
        Captures per batch.
    shells : list of int, optional
        Captures per shell, centre-out (default :func:`shell_sizes`). Each shell
        is split and visited before the next; small shells near DC keep the
        order close to strictly centre-out, large ones far out need fewer phases.
    lanes : int
        Most lanes a phase may hold (1, 2, 4 or 8: the threads that run them side by side).

    Returns
    -------
    Schedule
    """
    if lanes not in (1, 2, 4, 8):
        raise ValueError(f"lanes must be 1, 2, 4 or 8, got {lanes}")
    depth = int(np.log2(lanes))
    everything = np.argsort(distances, kind="stable")
    groups = []
    sizes = shell_sizes(everything.size, batch) if shells is None else shells
    edges = np.minimum(np.cumsum([0] + list(sizes)), everything.size)
    for start, stop in zip(edges[:-1], edges[1:]):
        if stop == start:
            continue
        members = everything[start:stop]
        groups += _phases(box_origins, box_size, members, (0, 1), max(depth, 1)) if depth else [[members]]
    order, phases, start = [], [], 0
    for group in groups:
        phase_lanes = []
        for members in group:
            if members.size == 0:
                continue
            phase_lanes.append(tuple(slice(start + s.start, start + s.stop)
                                     for s in _full_batches(members.size, batch)))
            order.append(members)
            start += members.size
        if phase_lanes:
            phases.append(Phase(tuple(phase_lanes)))
    return Schedule(np.concatenate(order).astype(np.int64), tuple(phases))


def _phases(box_origins: np.ndarray, box_size: int, members: np.ndarray, axes: tuple[int, ...],
            depth: int) -> list[list[np.ndarray]]:
    """Phases (run in turn) of lanes (run side by side) of ``members``, split ``depth`` more times.

    ``axes`` are the axes along which the members may still be told apart: a seam's boxes all straddle
    its line, so only the other axis can split it further. The seam runs first (it lies nearer DC),
    then the two sides side by side, each split the same way.
    """
    if depth == 0 or members.size < 2 or not axes:
        return [[members]]
    axis, other = axes[0], tuple(a for a in axes if a != axes[0])
    before, after, seam = split_disjoint(box_origins[:, axis], box_size, members)
    seam_phases = _phases(box_origins, box_size, seam, other, depth) if seam.size else []
    turned = other + (axis,)
    sides = [_phases(box_origins, box_size, part, turned, depth - 1) for part in (before, after) if part.size]
    merged = [sum((side[i] for side in sides if i < len(side)), []) for i in range(max(map(len, sides), default=0))]
    return seam_phases + merged
