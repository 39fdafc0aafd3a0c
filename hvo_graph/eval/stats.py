"""Summary statistics for the Monte Carlo experiments: RMSE, Student-t confidence intervals.

No SciPy: the Student t quantile is computed here.

- For integer degrees of freedom nu <= :data:`EXACT_DF_LIMIT` the two-sided t
  distribution function has a closed form (Abramowitz & Stegun 26.7.3 and
  26.7.4; theta = arctan(t / sqrt(nu))):

      A(t | nu) = P(|T| <= t)
                = 2 theta / pi                                              nu = 1
                = 2/pi [theta + sin theta (cos theta + 2/3 cos^3 theta + ...
                        + (2 4 ... (nu-3)) / (1 3 ... (nu-2)) cos^(nu-2) theta)]   nu odd >= 3
                = sin theta [1 + 1/2 cos^2 theta + (1 3)/(2 4) cos^4 theta + ...
                        + (1 3 ... (nu-3)) / (2 4 ... (nu-2)) cos^(nu-2) theta]      nu even

  and the quantile is found by bisection on this monotone function to machine
  precision (the result matches the printed tables to every digit).
- Beyond that, the Cornish-Fisher expansion of t in powers of 1/nu around the
  normal quantile z (A&S 26.7.5, four terms), whose error is below 1e-10 for
  nu > 1000; z itself is found by bisection on Phi(z) = erfc(-z / sqrt 2) / 2.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hvo_graph.errors import InputError, as_integer

#: Degrees of freedom up to which :func:`t_quantile` inverts the exact distribution function.
EXACT_DF_LIMIT = 1000


def _finite_values(values: object, name: str) -> np.ndarray:
    """(N,) float array, N >= 1, all finite; InputError naming ``name`` otherwise."""
    try:
        x = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a sequence of numbers") from None
    if x.ndim != 1:
        raise InputError(f"{name}: expected a 1-D sequence of numbers, got shape {x.shape}")
    if x.size == 0:
        raise InputError(f"{name}: expected at least one value, got none")
    if not np.all(np.isfinite(x)):
        bad = int(np.flatnonzero(~np.isfinite(x))[0])
        raise InputError(f"{name}: value {bad} is not finite ({x[bad]})")
    return x


def rmse(errors: Sequence[float] | np.ndarray) -> float:
    """Root mean square sqrt(mean_k e_k^2) of per-frame errors e, shape (K,), K >= 1.

    Raises:
        InputError: empty, not 1-D, or a non-finite value.
    """
    e = _finite_values(errors, "errors")
    return float(math.sqrt(np.mean(e * e)))


def _two_sided_cdf(t: float, df: int) -> float:
    """A(t | df) = P(|T| <= t) for t >= 0 and integer df >= 1 (A&S 26.7.3-4, module docstring)."""
    theta = math.atan(t / math.sqrt(df))
    s, c2 = math.sin(theta), math.cos(theta) ** 2
    if df % 2 == 0:
        # 1 + 1/2 c^2 + (1 3)/(2 4) c^4 + ...: term_j = term_{j-1} (2j - 1)/(2j) c^2
        term, total = 1.0, 1.0
        for j in range(1, df // 2):
            term *= (2 * j - 1) / (2 * j) * c2
            total += term
        return s * total
    if df == 1:
        return 2.0 * theta / math.pi
    # cos + 2/3 cos^3 + (2 4)/(3 5) cos^5 + ...: term_j = term_{j-1} (2j)/(2j + 1) c^2
    term = math.cos(theta)
    total = term
    for j in range(1, (df - 1) // 2):
        term *= (2 * j) / (2 * j + 1) * c2
        total += term
    return 2.0 / math.pi * (theta + s * total)


def _bisect(f: object, target: float, lo: float, hi: float) -> float:
    """x in [lo, hi] with f(x) = target for increasing f, to the last representable bit."""
    for _ in range(1100):  # widen until bracketed; 2^1100 overflows, so this ends
        if not f(hi) < target or math.isinf(hi):  # type: ignore[operator]
            break
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if f(mid) < target:  # type: ignore[operator]
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def normal_quantile(p: float) -> float:
    """z with Phi(z) = p for the standard normal, 0 < p < 1 (bisection on erfc)."""
    p = _probability(p)
    if p == 0.5:
        return 0.0
    upper = p > 0.5
    q = p if upper else 1.0 - p
    z = _bisect(lambda x: 0.5 * math.erfc(-x / math.sqrt(2.0)), q, 0.0, 1.0)
    return z if upper else -z


def _probability(p: object) -> float:
    try:
        value = float(p)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"p: expected a probability in (0, 1), got {p!r}") from None
    if not 0.0 < value < 1.0:
        raise InputError(f"p: expected a probability in (0, 1), got {p!r}")
    return value


def t_quantile(p: float, df: int) -> float:
    """Quantile t_{p, df} of Student's t distribution: P(T <= t) = p.

    Args:
        p: probability, 0 < p < 1 (e.g. 0.975 for a two-sided 95 % interval).
        df: degrees of freedom, an integer >= 1.
    Returns:
        t; e.g. t_quantile(0.975, 4) = 2.776 (textbook tables).
    Raises:
        InputError: p outside (0, 1) or df not an integer >= 1.
    """
    p = _probability(p)
    df = as_integer(df, "df", 1)
    if p == 0.5:
        return 0.0
    upper = p > 0.5
    q = p if upper else 1.0 - p  # P(T <= t) = q >= 1/2 with t >= 0, i.e. A(t) = 2q - 1
    if df <= EXACT_DF_LIMIT:
        t = _bisect(lambda x: _two_sided_cdf(x, df), 2.0 * q - 1.0, 0.0, 1.0)
    else:
        z, n = normal_quantile(q), float(df)
        g1 = (z**3 + z) / 4.0
        g2 = (5 * z**5 + 16 * z**3 + 3 * z) / 96.0
        g3 = (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / 384.0
        g4 = (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / 92160.0
        t = z + g1 / n + g2 / n**2 + g3 / n**3 + g4 / n**4
    return t if upper else -t


@dataclass(frozen=True)
class MeanCI:
    """Sample mean with a Student-t confidence interval.

    Attributes:
        mean: sample mean x_bar of the n values.
        half_width: t_{(1 + c)/2, n-1} s / sqrt(n), s the sample standard deviation
            (ddof = 1); NaN when n = 1 (no spread to estimate).
        n: number of values.
        confidence: c, e.g. 0.95.
    """

    mean: float
    half_width: float
    n: int
    confidence: float = 0.95

    @property
    def low(self) -> float:
        """mean - half_width."""
        return self.mean - self.half_width

    @property
    def high(self) -> float:
        """mean + half_width."""
        return self.mean + self.half_width


def mean_ci(values: Sequence[float] | np.ndarray, confidence: float = 0.95) -> MeanCI:
    """Mean of ``values`` (N,) and its Student-t confidence interval.

    x_bar +- t_{(1 + c)/2, N-1} s / sqrt(N), s = sqrt(sum (x - x_bar)^2 / (N - 1)):
    the interval for the mean of i.i.d. normal values (and, by the central limit
    theorem, approximately for others).

    Raises:
        InputError: empty, not 1-D, a non-finite value, or confidence outside (0, 1).
    """
    x = _finite_values(values, "values")
    try:
        c = float(confidence)
    except (TypeError, ValueError):
        c = math.nan
    if not 0.0 < c < 1.0:
        raise InputError(f"confidence: expected a number in (0, 1), got {confidence!r}")
    n = x.size
    mean = float(np.mean(x))
    if n == 1:
        return MeanCI(mean, math.nan, 1, c)
    s = float(np.std(x, ddof=1))
    return MeanCI(mean, t_quantile(0.5 * (1.0 + c), n - 1) * s / math.sqrt(n), n, c)
