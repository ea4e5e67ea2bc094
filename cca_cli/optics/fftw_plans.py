"""FFTW plans owned by one buffer: how hard to plan, the wisdom cache, one planner lock, raw plans.

:mod:`cca_cli.optics.fft` builds its transforms on this module; nothing else uses it directly.

Planning
--------
FFTW can find faster plans by timing candidates, but a timed search may pick
another algorithm on another run, and another algorithm rounds differently.
``$CCA_FFTW_PLANNING`` sets how plans are made:

* ``exact`` (default): results bit-identical to ``estimate``'s, often
  faster. A transform starts with its estimated plan; while the transforms
  run, a timed plan is searched for the most used ones (the same steps and
  budget as ``auto``, below) and kept only if it rounds exactly as the
  estimated plan does: both transform one random probe on a scratch buffer
  and must agree bit for bit. Timed plans often differ from the estimated one
  only in loop order and buffering (same codelets, same arithmetic), and are
  then up to twice as fast. The plans that passed, and the transforms whose
  timed plans did not, are kept in ``$CCA_CACHE_DIR`` (default
  ``~/.cache/cca``) with the machine they were reached on (CPU model and
  instruction sets, FFTW build); a plan kept by another machine is checked
  again before its first use. FFTW's own wisdom stays empty in between, so every
  estimated plan is the one a fresh process makes.
* ``estimate``: FFTW's estimated plans, made without timing and
  without the saved wisdom, so the same inputs and thread count give
  bit-identical results on every run and every machine with the same FFTW
  build.
* ``auto`` (opt-in, faster, not reproducible): a transform starts with the
  best plan FFTW already knows for its shape (the wisdom kept in
  ``$CCA_CACHE_DIR``, default ``~/.cache/cca``) or else an estimated plan.
  While the transforms run, their plans are improved one at a time, first to
  ``measure`` and then to ``patient`` quality, each step at most
  :data:`STEP_SECONDS` long and only while planning has cost less than
  :data:`UPGRADE_SHARE` of the time the transforms ran (and, beyond
  :data:`SHAPE_SECONDS` per shape, less than :data:`LONG_RUN_SHARE`). A plan
  improved mid-run changes the rounding from then on, so two runs of the same
  inputs may stop at other iterations with slightly other results.
* ``measure`` or ``patient`` (opt-in): plan at that effort when the transform
  is made (``patient`` takes seconds per new shape), from the wisdom when it
  holds a plan of that quality. Each run uses one plan per transform
  throughout, but which plan depends on the timings and the wisdom.

Timed planning runs on a scratch copy of the buffer, so planning never
touches the data.

Thread safety and lifetime
--------------------------
FFTW's planner is not thread-safe. Every planner call made here (pyfftw and
raw plans, their destruction, wisdom import and export, the planner's thread
count) holds :data:`PLANNER_LOCK`. pyfftw's own planner lock is private to
its extension module and FFTW's ``make_planner_thread_safe`` does nothing in
the OpenMP build pyfftw ships, so this lock is the process-wide one: the
pyfftw plans made here are also destroyed while holding it.

A :class:`PlanSet` holds the buffer, its pyfftw plans and its raw plans and
destroys them together; raw plan addresses reach compiled code only through
:meth:`RawFFTPlans.executing`, which keeps them alive and unchanged meanwhile.
"""

from __future__ import annotations

import bisect
import contextlib
import ctypes
import hashlib
import os
import pickle
import platform
import tempfile
import threading
import time
import weakref
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cca_cli.optics import switches
from cca_cli.optics.hidden_imports import hidden_in_this_thread, is_the_command

__all__ = ["HAVE_PYFFTW", "PLANNER_LOCK", "STEP_SECONDS", "UPGRADE_SHARE", "SHAPE_SECONDS", "LONG_RUN_SHARE",
           "planning_seconds", "raw_fftw_available", "Spec", "PlanSet", "owned_plans", "release", "RawFFTPlans"]


#: What pyfftw's package imports for interfaces cca never uses: ``dask.array`` (about 0.5 s), and, in the
#: ``cca`` command (which runs no one else's code), scipy through ``scipy.fftpack``.
_HIDDEN_WHILE_PYFFTW_LOADS = ("dask",)
_HIDDEN_IN_THE_COMMAND = ("scipy",)


def _import_pyfftw():
    """pyfftw, or None where it is not installed.

    pyfftw's package imports its optional dask and scipy interfaces whenever those are
    installed; cca never uses them. So they are hidden from the importing thread while pyfftw
    loads (:mod:`cca_cli.optics.hidden_imports`), and pyfftw leaves the interfaces out. Should
    pyfftw ever need them to load, it is imported again with them in view.
    """
    try:
        hidden = _HIDDEN_WHILE_PYFFTW_LOADS + (_HIDDEN_IN_THE_COMMAND if is_the_command() else ())
        with hidden_in_this_thread(hidden):
            import pyfftw as module
    except ImportError:  # pragma: no cover
        try:
            import pyfftw as module
        except ImportError:
            return None
    return module


pyfftw = None
if switches.read_at_import("CCA_FFT_BACKEND", "pyfftw", ("pyfftw", "scipy")) == "pyfftw":
    pyfftw = _import_pyfftw()

#: Whether pyfftw is installed and enabled (``CCA_FFT_BACKEND`` is not ``scipy``).
HAVE_PYFFTW = pyfftw is not None

#: Held by every FFTW planner call made here (see the module notes).
PLANNER_LOCK = threading.RLock()

#: Longest single planning step (s): Ctrl-C is answered within about this time.
STEP_SECONDS = 2.0
#: With ``auto`` planning, the most time spent improving the plans of a shape, as a share of the time its
#: transforms ran, up to :data:`SHAPE_SECONDS` per process; beyond that, :data:`LONG_RUN_SHARE`.
UPGRADE_SHARE = 0.25
SHAPE_SECONDS = 3.0
LONG_RUN_SHARE = 0.1
#: Expected cost (s) of the next planning step of each level, refined by what steps actually cost.
_step_cost = {"measure": 0.05, "patient": 0.8}
_planning = {"seconds": 0.0}

_LEVELS = ("estimate", "measure", "patient")

#: ``exact`` planning: per transform key, ("measure" | "patient", wisdom) for a timed plan that rounds as the
#: estimated plan, or ("rejected", level) for one that did not; shared by the process and the cache file.
_exact_plans: dict = {}
#: Keys whose ``_exact_plans`` entry was checked on this machine (entries from another machine's cache are checked
#: before their first use).
_exact_checked: set = set()
_exact_loaded = False
#: Seed of the probe that a timed plan and the estimated plan must transform to the same bits.
_PROBE_SEED = 20161


def planning_seconds() -> float:
    """Seconds this process has spent in timed FFTW planning so far."""
    return _planning["seconds"]


# ----------------------------------------------------------------------------- wisdom
def _wisdom_path() -> Path:
    """Where FFTW plans measured on this machine are kept between runs."""
    root = os.environ.get("CCA_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "cca")
    return Path(root) / f"fftw-wisdom-{pyfftw.__version__}.pickle"


class _BytesOnly(pickle.Unpickler):
    """Unpickles plain data only: a cache file holds tuples, dicts, strings and bytes and never names a class."""

    def find_class(self, module, name):
        raise pickle.UnpicklingError(f"unexpected {module}.{name} in an FFTW cache file")


def _read_cache_file(path: Path):
    """The plain data pickled in ``path``, or None when absent or unreadable."""
    try:
        with open(path, "rb") as handle:
            return _BytesOnly(handle).load()
    except Exception:  # noqa: BLE001 - a missing, truncated or foreign file only costs planning time
        return None


def _write_cache_file(path: Path, data) -> None:
    """Pickle ``data`` to ``path`` atomically (a temporary file renamed); a read-only or full cache is skipped."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("wb", dir=path.parent, delete=False, suffix=".tmp") as handle:
            pickle.dump(data, handle)
        os.replace(handle.name, path)
    except OSError:
        with contextlib.suppress(OSError, NameError):
            os.unlink(handle.name)  # a read-only or full cache only costs planning time


def _read_wisdom_file():
    """The wisdom saved in the cache (a tuple of bytes), or None when absent or unreadable."""
    wisdom = _read_cache_file(_wisdom_path())
    if isinstance(wisdom, tuple) and all(isinstance(part, bytes) for part in wisdom):
        return wisdom
    return None


_wisdom_loaded = False


def _load_wisdom() -> None:
    """Import the saved FFTW wisdom once per process (call with :data:`PLANNER_LOCK` held)."""
    global _wisdom_loaded
    if _wisdom_loaded:
        return
    _wisdom_loaded = True
    wisdom = _read_wisdom_file()
    if wisdom is not None:
        pyfftw.import_wisdom(wisdom)


def _save_wisdom() -> None:
    """Merge the process's wisdom with the cache file and write it atomically (with the lock held).

    Merging first keeps what concurrent processes (sweep workers) saved meanwhile.
    """
    on_disk = _read_wisdom_file()
    if on_disk is not None:
        pyfftw.import_wisdom(on_disk)
    wisdom = pyfftw.export_wisdom()
    if wisdom != on_disk:
        _write_cache_file(_wisdom_path(), wisdom)


def _exact_path() -> Path:
    """Where ``exact`` planning keeps its checked plans between runs."""
    return _wisdom_path().with_name(f"fftw-exact-{pyfftw.__version__}.pickle")


def _valid_exact_entry(key, entry) -> bool:
    """Whether a cache entry has the shape ``_exact_plans`` holds (a file may be damaged or foreign)."""
    if not (isinstance(key, tuple) and isinstance(entry, tuple) and len(entry) == 2):
        return False
    verdict, payload = entry
    if verdict == "rejected":
        return payload in _LEVELS[1:]
    return (verdict in _LEVELS[1:] and isinstance(payload, tuple)
            and all(isinstance(part, bytes) for part in payload))


_machine_id = None


def _machine() -> str:
    """What FFTW's plans and their rounding depend on here: the CPU (model, instruction sets) and the FFTW build."""
    global _machine_id
    if _machine_id is None:
        try:
            with open("/proc/cpuinfo") as info:
                lines = [line for line in info if line.startswith(("model name", "flags", "Features", "CPU part"))]
            cpu = "".join(sorted(set(lines)))
        except OSError:  # not Linux
            cpu = platform.processor()
        text = f"{platform.machine()}|{cpu}|pyfftw {pyfftw.__version__}"
        _machine_id = hashlib.blake2b(text.encode(), digest_size=12).hexdigest()
    return _machine_id


def _read_exact_file() -> tuple[str | None, dict]:
    """The machine the saved ``exact`` plans were checked on, and the plans; (None, {}) when absent or unreadable."""
    saved = _read_cache_file(_exact_path())
    if not (isinstance(saved, dict) and isinstance(saved.get("machine"), str) and isinstance(saved.get("plans"), dict)):
        return None, {}
    plans = {key: entry for key, entry in saved["plans"].items() if _valid_exact_entry(key, entry)}
    return saved["machine"], plans


def _load_exact() -> None:
    """Read the saved ``exact`` plans once per process (lock held).

    Plans checked on this machine are used as they are; plans from another machine (a home folder shared
    by several) are checked again before their first use, and its verdicts against timed plans are ignored.
    """
    global _exact_loaded
    if _exact_loaded:
        return
    _exact_loaded = True
    machine, plans = _read_exact_file()
    for key, entry in plans.items():
        if key in _exact_plans:
            continue
        if machine == _machine():
            _exact_plans[key] = entry
            _exact_checked.add(key)
        elif entry[0] != "rejected":
            _exact_plans[key] = entry


def _save_exact() -> None:
    """Merge this process's ``exact`` verdicts into the cache file, written atomically (lock held).

    Only verdicts reached on this machine are written; a file from another machine is replaced.
    """
    machine, on_disk = _read_exact_file()
    merged = dict(on_disk) if machine == _machine() else {}
    before = dict(merged)
    for key, entry in _exact_plans.items():
        if key in _exact_checked:
            merged[key] = entry
    if merged != before or machine != _machine():
        _write_cache_file(_exact_path(), {"machine": _machine(), "plans": merged})


def _forget_wisdom() -> None:
    """Empty FFTW's wisdom (lock held), so that the next estimated plan is the one a fresh process makes.

    ``auto``, ``measure`` and ``patient`` transforms made later read the cache file again.
    """
    global _wisdom_loaded
    pyfftw.forget_wisdom()
    _wisdom_loaded = False


@contextlib.contextmanager
def _wisdom_held(wisdom):
    """FFTW's wisdom is ``wisdom`` (None: none) inside the block and empty after it (lock held)."""
    _forget_wisdom()
    if wisdom:
        pyfftw.import_wisdom(wisdom)
    try:
        yield
    finally:
        _forget_wisdom()


# ----------------------------------------------------------------------------- FFTW library and planning
class _IODim(ctypes.Structure):
    _fields_ = [("n", ctypes.c_int), ("is_", ctypes.c_int), ("os", ctypes.c_int)]


_RAW_FLAGS = {"estimate": 1 << 6, "measure": 0, "patient": 1 << 5}
_FFTW_DESTROY_INPUT = 1
_FFTW_WISDOM_ONLY = 1 << 21
_FFTW_NO_TIMELIMIT = -1.0
_raw_library = None


def _fftw_library():
    """The single-precision FFTW that pyfftw loaded, through ctypes; None where it cannot be found.

    Plans made through it share pyfftw's wisdom, and compiled kernels can execute them
    without the interpreter (see :class:`RawFFTPlans`). Found through ``/proc/self/maps``,
    so only on Linux.
    """
    global _raw_library
    if not HAVE_PYFFTW:
        return None
    if _raw_library is not None:
        return _raw_library or None
    _raw_library = False
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "/libfftw3f" in line}
    except OSError:
        return None
    threaded = [p for p in paths if "_omp" in p or "_threads" in p]
    paths = [p for p in paths if p not in threaded]
    if len(paths) != 1 or len(threaded) > 1:
        return None
    try:
        library = ctypes.CDLL(paths[0])
        threads = ctypes.CDLL(threaded[0]) if threaded else None
        library.plan_with_nthreads = threads.fftwf_plan_with_nthreads if threads else None
        if library.plan_with_nthreads is not None:
            library.plan_with_nthreads.argtypes = [ctypes.c_int]
            library.plan_with_nthreads.restype = None
        # FFTW >= 3.3.9 reports the planner's thread count, so it can be put back after planning.
        library.planner_nthreads = getattr(threads, "fftwf_planner_nthreads", None) if threads else None
        if library.planner_nthreads is not None:
            library.planner_nthreads.argtypes = []
            library.planner_nthreads.restype = ctypes.c_int
        library.fftwf_plan_guru_dft.restype = ctypes.c_void_p
        library.fftwf_plan_guru_dft.argtypes = [ctypes.c_int, ctypes.POINTER(_IODim), ctypes.c_int,
                                                ctypes.POINTER(_IODim), ctypes.c_void_p, ctypes.c_void_p,
                                                ctypes.c_int, ctypes.c_uint]
        library.fftwf_execute.argtypes = [ctypes.c_void_p]
        library.fftwf_execute.restype = None
        library.fftwf_destroy_plan.argtypes = [ctypes.c_void_p]
        library.fftwf_destroy_plan.restype = None
        library.fftwf_set_timelimit.argtypes = [ctypes.c_double]
        library.fftwf_set_timelimit.restype = None
        library.execute_address = int(ctypes.cast(library.fftwf_execute, ctypes.c_void_p).value)
    except (OSError, AttributeError):
        return None
    _raw_library = library
    return library


def raw_fftw_available() -> bool:
    """Whether raw FFTW plans (for compiled loops) can be made here: pyfftw, Linux, ``CCA_RAW_FFTW`` not off."""
    return switches.raw_fftw_enabled() and _fftw_library() is not None


@contextlib.contextmanager
def _single_threaded_planning(library):
    """Plan with one thread and no time limit (with the lock held), then put the thread count back.

    The thread count and time limit are planner-wide settings. pyfftw sets both before
    each of its plans; FFTW >= 3.3.9 reports the count, which is then restored. Older
    versions cannot report it and keep 1, FFTW's default.
    """
    previous = library.planner_nthreads() if library.planner_nthreads is not None else None
    if library.plan_with_nthreads is not None:
        library.plan_with_nthreads(1)
    library.fftwf_set_timelimit(_FFTW_NO_TIMELIMIT)
    try:
        yield
    finally:
        if previous is not None and previous != 1:
            library.plan_with_nthreads(previous)


class Spec(NamedTuple):
    """One in-place transform of a view of a buffer."""

    count: int | None  # leading fields transformed (None: the whole buffer)
    rows: tuple[int, int] | None  # band of rows of the last-but-one axis (None: all)
    axes: tuple[int, ...]  # transformed axes, negative
    sign: int  # -1 forward, +1 inverse

    def view(self, buffer: np.ndarray) -> np.ndarray:
        view = buffer if self.count is None else buffer[:self.count]
        return view if self.rows is None else view[..., self.rows[0]:self.rows[1], :]


def _scratch_like(buffer: np.ndarray) -> np.ndarray:
    """An array with ``buffer``'s shape and dtype at the same address alignment (FFTW keys wisdom on it)."""
    align = 64
    raw = np.empty(buffer.nbytes + align, np.uint8)
    shift = (buffer.ctypes.data - raw.ctypes.data) % align
    return raw[shift:shift + buffer.nbytes].view(buffer.dtype).reshape(buffer.shape)


def _pyfftw_plan(view, spec: Spec, threads: int, level: str, *, wisdom_only=False, timelimit=None):
    """A pyfftw plan of ``view`` (call with the lock held); None when ``wisdom_only`` and FFTW knows none."""
    flags = ["FFTW_" + level.upper(), "FFTW_DESTROY_INPUT"] + (["FFTW_WISDOM_ONLY"] if wisdom_only else [])
    direction = "FFTW_FORWARD" if spec.sign < 0 else "FFTW_BACKWARD"
    try:
        return pyfftw.FFTW(view, view, axes=spec.axes, direction=direction, flags=flags, threads=threads,
                           planning_timelimit=timelimit)
    except RuntimeError:
        if wisdom_only:
            return None
        raise


def _raw_plan(library, view: np.ndarray, spec: Spec, level: str) -> int:
    """A raw FFTW plan of ``view`` from wisdom at ``level`` (estimate: no wisdom needed); 0 if none.

    Neither way times anything, so the buffer is never touched. Call with the lock held.
    """
    ndim = view.ndim
    axes = [a % ndim for a in spec.axes]
    strides = [s // view.itemsize for s in view.strides]
    dims = [_IODim(view.shape[a], strides[a], strides[a]) for a in axes]
    loops = [_IODim(view.shape[a], strides[a], strides[a]) for a in range(ndim) if a not in axes]
    flags = _RAW_FLAGS[level] | _FFTW_DESTROY_INPUT | (0 if level == "estimate" else _FFTW_WISDOM_ONLY)
    start = view.ctypes.data
    with _single_threaded_planning(library):
        plan = library.fftwf_plan_guru_dft(len(dims), (_IODim * len(dims))(*dims), len(loops),
                                           (_IODim * max(1, len(loops)))(*loops), start, start, spec.sign, flags)
    return int(plan or 0)


def _fields(view: np.ndarray):
    """The 2-D fields of ``view`` (views into it, never copies)."""
    for index in np.ndindex(view.shape[:-2]):
        yield view[index]


def _fill_probe(view: np.ndarray) -> None:
    """Fill ``view`` with the same random complex values every time, one field at a time."""
    rng = np.random.default_rng(_PROBE_SEED)
    for field in _fields(view):
        field.real = rng.standard_normal(field.shape, np.float32)
        field.imag = rng.standard_normal(field.shape, np.float32)


def _digest(view: np.ndarray) -> bytes:
    """A digest of ``view``'s bits, read one field at a time (no copy of the whole view)."""
    digest = hashlib.blake2b(digest_size=32)
    for field in _fields(view):
        digest.update(np.ascontiguousarray(field).view(np.uint8))
    return digest.digest()


class _Budget:
    """Planning accounts shared by the transforms of one shape (what one finds, all adopt).

    ``busy`` is the longest time any one transform object of the shape ran: threads running
    transforms of one shape side by side wait for each other, so their times do not add up.
    """

    def __init__(self):
        self.busy = 0.0  # seconds the busiest transform object of the shape ran
        self.spent = 0.0  # seconds spent improving their plans
        self.next_check = _step_cost["measure"] / UPGRADE_SHARE  # busy seconds before the next improvement
        self.stuck: set[int] = set()  # transforms whose search ran out of time

    def allowance(self) -> float:
        """Seconds of planning the shape may still spend: its share of ``busy``, less what it spent."""
        limit = min(UPGRADE_SHARE * self.busy, max(SHAPE_SECONDS, LONG_RUN_SHARE * self.busy))
        return limit - self.spent

    def allows(self, cost: float) -> bool:
        """Whether a planning step of ``cost`` seconds fits; if not, when to ask again (``next_check``)."""
        if self.allowance() >= cost:
            return True
        total = self.spent + cost
        needed = total / UPGRADE_SHARE
        if total > SHAPE_SECONDS:
            needed = max(needed, total / LONG_RUN_SHARE)
        self.next_check = needed
        return False


_budgets: dict = {}


class PlanSet:
    """The FFTW plans of one buffer, their upkeep and their release: the owner behind a transform object.

    Holds the buffer, the pyfftw plans and (once asked for) the raw plans; all are
    destroyed together, with :data:`PLANNER_LOCK` held, by :meth:`release` or when the
    transform object is collected. ``lock`` serialises execution, plan upgrades and release.
    """

    def __init__(self, buffer: np.ndarray, specs: list[Spec], threads: int, effort: str):
        self.buffer = buffer
        self.specs = specs
        self.threads = threads
        self.improves = effort in ("auto", "exact")  # plans searched for while the transforms run
        self.exact = effort == "exact"
        self.fftw = [None] * len(specs)
        self.level = ["estimate"] * len(specs)
        self.wisdom = [None] * len(specs)  # ``exact``: the wisdom a timed plan in use was made from
        self.uses = [0] * len(specs)
        self.raw: list[int] | None = None
        self.raw_generation = 0
        self.raw_table: np.ndarray | None = None
        self.released = False
        self.busy = 0.0  # seconds these transforms ran
        self.budget = _budgets.setdefault((buffer.shape, tuple(specs), threads), _Budget())
        self.lock = threading.RLock()
        try:
            self._plan_all(effort)
        except BaseException:
            self.release()
            raise

    # ------------------------------------------------------------------ planning (lock held)
    def _adopt(self, i: int, level: str) -> bool:
        """Plan transform ``i`` on the buffer from wisdom at ``level``; False when FFTW has none."""
        spec = self.specs[i]
        plan = _pyfftw_plan(spec.view(self.buffer), spec, self.threads, level, wisdom_only=True)
        if plan is None:
            return False
        self.fftw[i], self.level[i] = plan, level  # the plan replaced is destroyed here, under the lock
        if self.raw is not None:
            self._replace_raw(i)
        return True

    def _search(self, indices, level: str, timelimit: float | None) -> float:
        """Time candidate plans of transforms ``indices`` at ``level`` on a scratch buffer; returns seconds."""
        scratch = _scratch_like(self.buffer)
        start = time.perf_counter()
        for i in indices:
            spec = self.specs[i]
            plan = _pyfftw_plan(spec.view(scratch), spec, self.threads, level, timelimit=timelimit)
            del plan
        seconds = time.perf_counter() - start
        _planning["seconds"] += seconds
        return seconds

    def _key(self, i: int) -> tuple:
        """What a timed plan of transform ``i`` depends on, as plain data (the ``exact`` cache's key)."""
        spec = self.specs[i]
        buffer = self.buffer
        return (tuple(buffer.shape), buffer.dtype.str, buffer.ctypes.data % 64, spec.count, spec.rows,
                tuple(spec.axes), spec.sign, self.threads)

    def _plan_exact(self) -> None:
        """``exact``: estimated plans, then the checked timed plans known for these transforms (lock held)."""
        _forget_wisdom()
        _load_exact()
        for i, spec in enumerate(self.specs):
            self.fftw[i] = _pyfftw_plan(spec.view(self.buffer), spec, self.threads, "estimate")
        for i in range(len(self.specs)):
            entry = _exact_plans.get(self._key(i))
            if entry is not None and (entry[0] == "rejected" or not self._adopt_exact(i)):
                self.budget.stuck.add(i)

    def _rounds_exactly(self, i: int, level: str, wisdom=None, timelimit=None):
        """Whether a plan of transform ``i`` at ``level`` rounds as its estimated plan; ``(same, wisdom)``.

        The plan is searched for (timed, within ``timelimit``) unless ``wisdom`` holds it. Both
        plans transform the same random probe on a scratch buffer; FFTW's wisdom is empty
        afterwards. ``wisdom`` is None when the plan could not be made from it.
        """
        spec = self.specs[i]
        scratch = _scratch_like(self.buffer)
        view = spec.view(scratch)
        _forget_wisdom()
        reference = _pyfftw_plan(view, spec, self.threads, "estimate")
        _forget_wisdom()
        if wisdom is None:
            start = time.perf_counter()
            try:
                candidate = _pyfftw_plan(view, spec, self.threads, level, timelimit=timelimit)
                wisdom = pyfftw.export_wisdom()
            finally:
                _forget_wisdom()
                _planning["seconds"] += time.perf_counter() - start
        else:
            with _wisdom_held(wisdom):
                candidate = _pyfftw_plan(view, spec, self.threads, level, wisdom_only=True)
            if candidate is None:
                return False, None
        _fill_probe(view)
        reference.execute()
        expected = _digest(view)
        _fill_probe(view)
        candidate.execute()
        return _digest(view) == expected, wisdom

    def _adopt_exact(self, i: int) -> bool:
        """Use the timed plan ``_exact_plans`` holds for transform ``i``, checked first unless this machine did."""
        key = self._key(i)
        level, wisdom = _exact_plans[key]
        if key not in _exact_checked:
            same, _ = self._rounds_exactly(i, level, wisdom)
            _exact_checked.add(key)
            if not same:
                _exact_plans[key] = ("rejected", level)
                return False
        spec = self.specs[i]
        with _wisdom_held(wisdom):
            plan = _pyfftw_plan(spec.view(self.buffer), spec, self.threads, level, wisdom_only=True)
        if plan is None:
            return False
        self.fftw[i], self.level[i], self.wisdom[i] = plan, level, wisdom
        if self.raw is not None:
            self._replace_raw(i)
        return True

    def _improve_exact(self, i: int) -> None:
        """One ``exact`` planning step for transform ``i``: search a timed plan, keep it if it rounds the same."""
        budget = self.budget
        key = self._key(i)
        entry = _exact_plans.get(key)
        if entry is not None:  # another transform of the same shape searched already
            if entry[0] == "rejected" or not self._adopt_exact(i):
                budget.stuck.add(i)
            return
        if not budget.allows(_step_cost["measure"]):
            return
        timelimit = min(STEP_SECONDS, max(budget.allowance(), 2 * _step_cost["measure"]))
        start = time.perf_counter()
        try:
            same, wisdom = self._rounds_exactly(i, "measure", timelimit=timelimit)
        except RuntimeError:  # an improvement is optional: keep the plans in use
            same, wisdom = False, None
        seconds = time.perf_counter() - start
        budget.spent += seconds
        _step_cost["measure"] = 0.5 * _step_cost["measure"] + 0.5 * seconds
        if wisdom is not None:
            _exact_plans[key] = ("measure", wisdom) if same else ("rejected", "measure")
            _exact_checked.add(key)
            if same and self._adopt_exact(i):
                _save_exact()
                return
            if not same:
                _save_exact()
                budget.stuck.add(i)
                return
            del _exact_plans[key]  # the search was cut short: FFTW kept no wisdom of it
        if timelimit >= STEP_SECONDS:
            budget.stuck.add(i)
        else:
            _step_cost["measure"] = max(_step_cost["measure"], 2 * seconds)

    def _plan_all(self, effort: str) -> None:
        with PLANNER_LOCK:
            if self.exact:
                self._plan_exact()
                return
            if effort != "estimate":  # estimated plans never see the wisdom: the same plans on every run
                _load_wisdom()
            n = len(self.specs)
            wanted = "patient" if effort == "auto" else effort
            known = [i for i in range(n) if wanted != "estimate" and self._adopt(i, wanted)]
            missing = [i for i in range(n) if i not in known]
            if self.improves:  # auto (exact returned above): the best plan on file, else an estimate; no timing now
                missing = [i for i in missing if not self._adopt(i, "measure")]
            elif wanted != "estimate" and missing:
                self._search(missing, wanted, timelimit=None)
                missing = [i for i in missing if not self._adopt(i, wanted)]
                _save_wisdom()
            for i in missing:
                spec = self.specs[i]
                self.fftw[i] = _pyfftw_plan(spec.view(self.buffer), spec, self.threads, "estimate")
                self.level[i] = "estimate"

    def _replace_raw(self, i: int) -> None:
        """Re-plan raw plan ``i`` at its transform's level and destroy the old one (lock held)."""
        library = _fftw_library()
        spec = self.specs[i]
        view = spec.view(self.buffer)
        if self.exact:  # from the plan's own wisdom, or with none (then the estimated plan of a fresh process)
            with _wisdom_held(self.wisdom[i]):
                plan = _raw_plan(library, view, spec, self.level[i])
        else:
            plan = _raw_plan(library, view, spec, self.level[i]) or _raw_plan(library, view, spec, "estimate")
        if not plan:
            raise RuntimeError("FFTW could not plan a transform")
        old, self.raw[i] = self.raw[i], plan
        if old:
            library.fftwf_destroy_plan(old)
        self.raw_table = None

    # ------------------------------------------------------------------ use
    def check_alive(self) -> None:
        if self.released:
            raise RuntimeError("this FFT's plans were released; make a new transform object")

    def note_use(self, seconds: float, used) -> None:
        """Count a run of transforms ``used`` (indices) lasting ``seconds``; improve a plan when it pays."""
        budget = self.budget
        self.busy += seconds
        if self.busy > budget.busy:
            budget.busy = self.busy
        for i in used:
            self.uses[i] += 1
        if self.improves and budget.busy >= budget.next_check:
            self._improve_one()

    def _improve_one(self) -> None:
        """One planning step: a used transform goes one level up (``lock`` held).

        Transforms still at ``estimate`` come first (measuring is cheap and gains most), then
        the most used. A step that times plans is taken only while the planning of this
        shape stays within its share of the time the transforms ran (see :data:`UPGRADE_SHARE`);
        a plan another transform of the same shape already found is adopted for free.
        """
        budget = self.budget
        top = "measure" if self.exact else "patient"
        pending = [i for i in range(len(self.specs))
                   if self.uses[i] and self.level[i] != top and i not in budget.stuck]
        if not pending:
            budget.next_check = budget.busy + _step_cost["measure"] / UPGRADE_SHARE
            return
        i = max(pending, key=lambda j: (-_LEVELS.index(self.level[j]), self.uses[j]))
        target = _LEVELS[_LEVELS.index(self.level[i]) + 1]
        with PLANNER_LOCK:
            if self.exact:
                self._improve_exact(i)
                return
            if self._adopt(i, target) or not budget.allows(_step_cost[target]):
                return
            # The budget caps the step, though not below twice its expected cost (a search cut
            # short finds nothing): planning may end up past the share by about one step.
            timelimit = min(STEP_SECONDS, max(budget.allowance(), 2 * _step_cost[target]))
            start = time.perf_counter()
            try:
                self._search([i], target, timelimit=timelimit)
                found = self._adopt(i, target)
            except RuntimeError:  # an improvement is optional: keep the plans in use
                found = False
            seconds = time.perf_counter() - start
            budget.spent += seconds
            _step_cost[target] = 0.5 * _step_cost[target] + 0.5 * seconds
            if found:
                _save_wisdom()
            elif timelimit >= STEP_SECONDS:  # too slow even for a whole step: keep the plans this process has
                budget.stuck.add(i)
            else:  # cut short by the budget: try again when the run has earned more (at the higher cost)
                _step_cost[target] = max(_step_cost[target], 2 * seconds)

    # ------------------------------------------------------------------ raw plans
    def make_raw(self) -> None:
        """Raw plans of every transform, from the wisdom of their pyfftw plans (lock held by caller)."""
        if self.raw is not None:
            return
        with PLANNER_LOCK:
            self.raw = [0] * len(self.specs)
            try:
                for i in range(len(self.specs)):
                    self._replace_raw(i)
            except BaseException:
                self.release_raw()
                raise
            self.raw_generation += 1

    def table(self, shape) -> np.ndarray:
        """The raw plan addresses as an int64 array of ``shape`` (rebuilt after a plan changes)."""
        if self.raw_table is None:
            self.raw_table = np.array(self.raw, dtype=np.int64).reshape(shape)
        return self.raw_table

    def release_raw(self) -> None:
        with PLANNER_LOCK:
            library = _fftw_library() if self.raw else None
            for plan in self.raw or ():
                if plan:
                    library.fftwf_destroy_plan(plan)
            self.raw = None
            self.raw_table = None
            self.raw_generation += 1

    def release(self) -> None:
        """Destroy every plan (idempotent); execution afterwards raises instead of crashing."""
        with PLANNER_LOCK:
            self.released = True
            self.release_raw()
            self.fftw = [None] * len(self.specs)  # pyfftw plans are destroyed here, under the lock


def release(plans: PlanSet) -> None:
    """Destroy ``plans`` now (waits for compiled code running them to finish)."""
    with plans.lock:
        plans.release()


def owned_plans(owner, buffer: np.ndarray, specs: list[Spec], threads: int, effort: str | None) -> PlanSet:
    """A :class:`PlanSet` for ``buffer`` that is released when ``owner`` is collected.

    ``effort`` defaults to :func:`~cca_cli.optics.switches.planning_effort`.
    """
    effort = effort or switches.planning_effort()
    efforts = switches.PLANNING_EFFORTS
    if effort not in efforts:
        raise ValueError(f"unknown FFTW planning effort {effort!r}; choose one of {', '.join(efforts)}")
    plans = PlanSet(buffer, specs, threads, effort)
    weakref.finalize(owner, release, plans).atexit = False
    return plans


class RawFFTPlans:
    """Raw FFTW plans of a buffer, for compiled code; the plans live as long as this object.

    Made by :meth:`cca_cli.optics.fft.BandedFFT2.raw_plans`, it keeps that transform object
    (and so its buffer and pyfftw plans) alive. Compiled code gets the plan addresses only
    inside :meth:`executing`, which holds the plans unchanged for the duration; after
    :meth:`release` (or the transform's ``close``) executing raises RuntimeError instead of
    crashing.

    Attributes
    ----------
    counts : ndarray, int64, (n,)
        The planned field counts, ascending.
    buffer : ndarray, complex64, (c, m, m)
        The buffer the plans transform.
    """

    def __init__(self, owner, plans: PlanSet, counts: list[int]):
        self._owner = owner  # keeps the transform object, and with it the plans, alive
        self._plans = plans
        self._count_list = list(counts)
        self.generation = plans.raw_generation
        self.counts = np.array(counts, dtype=np.int64)
        self.buffer = plans.buffer
        self.execute_address = _fftw_library().execute_address

    @property
    def released(self) -> bool:
        """Whether these plans were destroyed."""
        plans = self._plans
        return plans.released or plans.raw is None or plans.raw_generation != self.generation

    def release(self) -> None:
        """Destroy the raw plans now (the transform's own methods keep working)."""
        plans = self._plans
        with plans.lock:
            if plans.raw_generation == self.generation:
                plans.release_raw()

    def check_buffer(self, fields: np.ndarray) -> None:
        """Raise ValueError unless ``fields`` is the buffer the plans were made for."""
        buffer = self.buffer
        if not (fields is buffer or (isinstance(fields, np.ndarray) and fields.dtype == buffer.dtype
                                     and fields.shape == buffer.shape and fields.strides == buffer.strides
                                     and fields.ctypes.data == buffer.ctypes.data)):
            raise ValueError("fields must be the buffer these FFTW plans were made for "
                             f"({buffer.dtype} {buffer.shape}); got another array")

    def executing(self, fields: np.ndarray) -> _PlansInUse:
        """Hold the plans for compiled code that transforms ``fields`` (a context manager).

        Entering gives an object with ``execute`` (the address of ``fftwf_execute``),
        ``counts`` and ``plans``: the plan addresses, int64 (n, 4) — inverse rows and columns,
        forward columns and rows for each count. The plans stay alive and unchanged until
        the block ends. Set its ``largest`` to the most fields a batch transformed: the
        time spent counts as use of the plans of that count.

        Raises
        ------
        ValueError
            If ``fields`` is not the planned buffer.
        RuntimeError
            If the plans were released.
        """
        self.check_buffer(fields)
        return _PlansInUse(self)

    def execute(self, count: int, step: int) -> None:
        """Run one plan from the interpreter: ``step`` (0–3, in :meth:`executing`'s order) of planned ``count``."""
        index = int(np.searchsorted(self.counts, count))
        if index >= len(self.counts) or self.counts[index] != count or not 0 <= step < 4:
            raise ValueError(f"no plan for count {count}, step {step}; counts are {self.counts.tolist()}")
        plans = self._plans
        with plans.lock:
            if self.released:
                raise RuntimeError("these raw FFTW plans were released; ask the transform for new ones")
            _fftw_library().fftwf_execute(plans.raw[4 * index + step])


class _PlansInUse:
    """The raw plans held for compiled code by :meth:`RawFFTPlans.executing`."""

    __slots__ = ("_raw", "_plans", "execute", "counts", "plans", "largest", "_start")

    def __init__(self, raw: RawFFTPlans):
        self._raw = raw
        self._plans = raw._plans
        self.execute = raw.execute_address
        self.counts = raw.counts
        self.largest = int(raw.counts[-1])

    def __enter__(self) -> _PlansInUse:
        plans = self._plans
        plans.lock.acquire()
        if self._raw.released:
            plans.lock.release()
            raise RuntimeError("these raw FFTW plans were released; ask the transform for new ones")
        self.plans = plans.table((len(self.counts), 4))
        self._start = time.perf_counter()
        return self

    def __exit__(self, kind, value, traceback) -> None:
        plans = self._plans
        try:
            if kind is None and self.largest > 0:
                group = 4 * bisect.bisect_left(self._raw._count_list, self.largest)
                plans.note_use(time.perf_counter() - self._start, (group, group + 1, group + 2, group + 3))
        finally:
            plans.lock.release()
