"""The one exception type users see for bad input.

Every check on user-supplied data (files, arrays, arguments) raises
:class:`InputError` with a one-line message that names the file, line, key or
argument and says what was expected. The command line turns it into a line on
stderr and exit code 2.
"""

from __future__ import annotations

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
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: contains NaN or inf")
    return a


def as_vector(array: object, name: str, size: int) -> np.ndarray:
    """Return ``array`` as a finite float vector of shape (size,), or raise InputError."""
    a = np.asarray(array, dtype=float)
    if a.shape != (size,):
        raise InputError(f"{name}: expected shape ({size},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: contains NaN or inf")
    return a


def as_matrix(array: object, name: str, shape: tuple[int, int]) -> np.ndarray:
    """Return ``array`` as a finite float matrix of the given shape, or raise InputError."""
    a = np.asarray(array, dtype=float)
    if a.shape != shape:
        raise InputError(f"{name}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: contains NaN or inf")
    return a
