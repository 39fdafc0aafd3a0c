"""The one exception type users see for bad input, and the checks that raise it.

Every check on user-supplied data (files, arrays, arguments) raises
:class:`InputError` with a one-line message that names the file, line, key or
argument and says what was expected. The command line turns it into a line on
stderr and exit code 2. The checks shared by every module live here: points,
vectors and matrices of a shape (:func:`as_points`, :func:`as_vector`,
:func:`as_matrix`), bounded numbers and integers (:func:`as_number`,
:func:`as_integer`), covariances (:func:`as_covariance`) and rotations
(:func:`as_rotation`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np


class InputError(ValueError):
    """Bad user input: the message names what is wrong and what was expected."""


def as_points(
    array: object, name: str, *, min_points: int = 1, dim: int | None = None
) -> np.ndarray:
    """Return ``array`` as a finite float array of shape (N, dim), or raise InputError.

    Args:
        array: array-like of shape (N, dim).
        name: argument name used in the error message.
        min_points: smallest accepted N.
        dim: required number of columns (None: 2 or 3).
    """
    a = np.asarray(array, dtype=float)
    dims = (dim,) if dim is not None else (2, 3)
    if a.ndim != 2 or a.shape[1] not in dims:
        want = " or ".join(f"(N, {d})" for d in dims)
        raise InputError(f"{name}: expected an array of shape {want}, got shape {a.shape}")
    if a.shape[0] < min_points:
        raise InputError(f"{name}: need at least {min_points} points, got {a.shape[0]}")
    if not _all_finite(a):
        raise InputError(f"{name}: contains NaN or inf")
    return a


def _all_finite(a: np.ndarray) -> bool:
    """Whether every entry is finite; small arrays (the per-frame vectors and matrices)
    through Python floats, which costs a third of numpy's call overhead."""
    if a.size <= 36:
        return all(map(math.isfinite, a.ravel().tolist()))
    return bool(np.isfinite(a).all())


def as_vector(array: object, name: str, size: int) -> np.ndarray:
    """Return ``array`` as a finite float vector of shape (size,), or raise InputError."""
    a = np.asarray(array, dtype=float)
    if a.shape != (size,):
        raise InputError(f"{name}: expected shape ({size},), got {a.shape}")
    if not _all_finite(a):
        raise InputError(f"{name}: contains NaN or inf")
    return a


def as_matrix(array: object, name: str, shape: tuple[int, int]) -> np.ndarray:
    """Return ``array`` as a finite float matrix of the given shape, or raise InputError."""
    a = np.asarray(array, dtype=float)
    if a.shape != shape:
        raise InputError(f"{name}: expected shape {shape}, got {a.shape}")
    if not _all_finite(a):
        raise InputError(f"{name}: contains NaN or inf")
    return a


def _shown(value: object) -> str:
    """How a rejected value appears in a message: floats plainly, anything else as repr."""
    return str(float(value)) if isinstance(value, float | np.floating) else repr(value)


def as_number(
    value: object,
    name: str,
    *,
    above: float | None = None,
    at_least: float | None = None,
    what: str = "a finite number",
    unit: str = "",
) -> float:
    """Return ``value`` as a finite float (> ``above`` or >= ``at_least``), or raise InputError.

    Args:
        value: a real number (Python or NumPy scalar; not a bool or a string).
        name: argument name used in the error message.
        above: exclusive lower bound, or None.
        at_least: inclusive lower bound, or None.
        what: how the message names the expected value, e.g. "a finite time step".
        unit: appended to the bound in the message, e.g. " s".
    """
    op, bound = (">", above) if above is not None else (">=", at_least)
    x = math.nan
    if not isinstance(value, bool | str | bytes) and np.ndim(value) == 0:
        try:
            x = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            pass
    if not math.isfinite(x) or (
        bound is not None and not (x > bound if above is not None else x >= bound)
    ):
        limit = "" if bound is None else f" {op} {bound:g}{unit}"
        raise InputError(f"{name}: expected {what}{limit}, got {_shown(value)}")
    return x


def as_choice(value: object, name: str, choices: Iterable[str], *, none: bool = False) -> None:
    """Raise InputError unless ``value`` is one of ``choices`` (or None, with ``none``)."""
    choices = tuple(choices)
    if not ((isinstance(value, str) and value in choices) or (none and value is None)):
        either = "None or one" if none else "one"
        raise InputError(f"{name}: expected {either} of {', '.join(choices)}, got {value!r}")


def as_integer(value: object, name: str, minimum: int, *, what: str = "an integer") -> int:
    """Return ``value`` as an int >= ``minimum`` (a Python or NumPy integer, not a bool)."""
    if (
        isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum  # type: ignore[operator]
    ):
        raise InputError(f"{name}: expected {what} >= {minimum}, got {value!r}")
    return int(value)


def as_covariance(matrix: object, name: str, size: int) -> np.ndarray:
    """Return ``matrix`` as a finite, symmetric, positive-definite (size, size) float array.

    Symmetric means max |C - C^T| <= 1e-9 max |C|; positive definite, that the
    Cholesky factorization exists. The array is returned as given, not symmetrized.
    """
    c = as_matrix(matrix, name, (size, size))
    if np.abs(c - c.T).max() > 1e-9 * np.abs(c).max():
        raise InputError(f"{name}: expected a symmetric matrix")
    try:
        np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        raise InputError(f"{name}: expected a positive definite matrix") from None
    return c


def as_rotation(matrix: object, name: str) -> np.ndarray:
    """Return ``matrix`` as a (3, 3) rotation: max |R^T R - I| <= 1e-6 and det R > 0."""
    R = as_matrix(matrix, name, (3, 3))
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
        raise InputError(f"{name}: expected a rotation matrix (R^T R = I, det R = +1)")
    return R
