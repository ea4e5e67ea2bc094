"""Environment switches of the array backend, checked with one-line errors.

========================  ==========================================  ===============================
variable                  values (default first)                      effect
========================  ==========================================  ===============================
``CCA_FFTW_PLANNING``     ``exact``, ``estimate``, ``auto``,          how FFTW plans (see
                          ``measure``, ``patient``                    :mod:`cca_cli.optics.fftw_plans`)
``CCA_FFT_BACKEND``       ``pyfftw``, ``scipy``                       ``scipy``: run without pyfftw
``CCA_KERNELS``           ``numba``, ``numpy``                        ``numpy``: run without numba
``CCA_RAW_FFTW``          ``on``, ``off``                             ``off``: run as where FFTW's
                                                                      library cannot be found
========================  ==========================================  ===============================

The last three select the fallbacks on any machine (the test suite runs them).
``CCA_FFT_BACKEND`` and ``CCA_KERNELS`` are read once, when their module is imported
(pyfftw or numba is then not imported at all); an unknown value is reported by
:func:`check`, which the transforms and kernels call before their first use.
"""

from __future__ import annotations

import os

from cca_cli.errors import ConfigError

__all__ = ["PLANNING_EFFORTS", "choice", "read_at_import", "check", "planning_effort", "raw_fftw_enabled"]

#: Accepted values of ``CCA_FFTW_PLANNING``.
PLANNING_EFFORTS = ("exact", "estimate", "auto", "measure", "patient")

_import_errors: list[ConfigError] = []


def choice(name: str, default: str, accepted: tuple[str, ...]) -> str:
    """The value of environment variable ``name`` (lower case; ``default`` when unset or empty).

    Raises
    ------
    ConfigError
        If the value is not one of ``accepted``: one line naming the variable and the accepted values.
    """
    given = os.environ.get(name, "")
    value = given.strip().lower() or default
    if value not in accepted:
        raise ConfigError(f"environment variable {name}={given!r} is not one of {', '.join(accepted)}; "
                          "unset it or pick one")
    return value


def read_at_import(name: str, default: str, accepted: tuple[str, ...]) -> str:
    """:func:`choice` for a switch read while a module is imported: an unknown value gives ``default``.

    The error is kept and raised by :func:`check`, so it reaches the user as one line
    instead of a traceback from an import.
    """
    try:
        return choice(name, default, accepted)
    except ConfigError as error:
        _import_errors.append(error)
        return default


def check() -> None:
    """Raise :class:`~cca_cli.errors.ConfigError` if any switch has an unknown value."""
    if _import_errors:
        raise _import_errors[0]
    raw_fftw_enabled()
    planning_effort()


def planning_effort() -> str:
    """How FFTW plans: ``$CCA_FFTW_PLANNING``, default ``"exact"`` (see :mod:`cca_cli.optics.fftw_plans`).

    Raises
    ------
    ConfigError
        If the variable names an unknown effort (one line naming the variable and the accepted values).
    """
    return choice("CCA_FFTW_PLANNING", "exact", PLANNING_EFFORTS)


def raw_fftw_enabled() -> bool:
    """Whether ``CCA_RAW_FFTW`` allows raw FFTW plans (default ``on``)."""
    return choice("CCA_RAW_FFTW", "on", ("on", "off")) == "on"
