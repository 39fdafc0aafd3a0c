"""RMSE, Student-t quantiles and confidence intervals against hand computations and tables."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hvo_graph.errors import InputError
from hvo_graph.eval.stats import EXACT_DF_LIMIT, mean_ci, normal_quantile, rmse, t_quantile

# Student t quantiles as printed in textbook tables (e.g. Montgomery & Runger,
# Applied Statistics and Probability for Engineers, Table V), 3 decimals.
TEXTBOOK_T = [
    # (p, df, t_{p, df})
    (0.975, 1, 12.706),
    (0.975, 2, 4.303),
    (0.975, 3, 3.182),
    (0.975, 4, 2.776),
    (0.975, 5, 2.571),
    (0.975, 9, 2.262),
    (0.975, 10, 2.228),
    (0.975, 19, 2.093),
    (0.975, 20, 2.086),
    (0.975, 30, 2.042),
    (0.975, 40, 2.021),
    (0.975, 60, 2.000),
    (0.975, 120, 1.980),
    (0.95, 4, 2.132),
    (0.95, 10, 1.812),
    (0.95, 30, 1.697),
    (0.90, 7, 1.415),
    (0.995, 1, 63.657),
    (0.995, 10, 3.169),
    (0.995, 25, 2.787),
    (0.9995, 15, 4.073),
]


@pytest.mark.parametrize(("p", "df", "expected"), TEXTBOOK_T)
def test_t_quantile_matches_textbook_table(p: float, df: int, expected: float) -> None:
    assert t_quantile(p, df) == pytest.approx(expected, abs=5e-4)


def test_t_quantile_matches_closed_forms_for_one_and_two_degrees_of_freedom() -> None:
    # df = 1 (Cauchy): t = tan(pi (p - 1/2)); df = 2: t = (2p - 1) / sqrt(2 p (1 - p)).
    for p in (0.6, 0.75, 0.9, 0.975, 0.999):
        assert t_quantile(p, 1) == pytest.approx(math.tan(math.pi * (p - 0.5)), rel=1e-12)
        assert t_quantile(p, 2) == pytest.approx(
            (2 * p - 1) / math.sqrt(2 * p * (1 - p)), rel=1e-12
        )


def test_t_quantile_is_odd_about_one_half_and_tends_to_the_normal() -> None:
    assert t_quantile(0.025, 4) == -t_quantile(0.975, 4)
    assert t_quantile(0.5, 7) == 0.0
    # Large df: the normal quantile z_0.975 = 1.959964 (textbook 1.960), z_0.995 = 2.575829.
    assert t_quantile(0.975, 10**6) == pytest.approx(1.959964, abs=5e-6)
    assert normal_quantile(0.975) == pytest.approx(1.959964, abs=1e-6)
    assert normal_quantile(0.995) == pytest.approx(2.575829, abs=1e-6)
    assert normal_quantile(0.025) == pytest.approx(-1.959964, abs=1e-6)
    # Both sides of the switch from the exact inversion to the Cornish-Fisher series:
    # tables give t_{0.975, 1000} = 1.962; the two branches agree to far below that.
    below, above = t_quantile(0.975, EXACT_DF_LIMIT), t_quantile(0.975, EXACT_DF_LIMIT + 1)
    assert below == pytest.approx(1.962, abs=5e-4)
    assert 0 < below - above < 1e-5


def test_t_quantile_agrees_with_sampled_t_distribution() -> None:
    # Independent of any table: the fraction of N(0,1) / sqrt(chi2_df / df) draws below
    # t_{p, df} is p (to sampling error, 4 standard errors).
    rng = np.random.default_rng(12345)
    samples = rng.standard_t(6, size=400_000)
    for p in (0.8, 0.95, 0.99):
        fraction = np.mean(samples <= t_quantile(p, 6))
        assert abs(fraction - p) < 4 * math.sqrt(p * (1 - p) / samples.size)


def test_rmse_hand_computation() -> None:
    # sqrt((3^2 + 4^2 + 0^2 + 12^2) / 4) = sqrt(169 / 4) = 6.5
    assert rmse([3.0, -4.0, 0.0, 12.0]) == pytest.approx(6.5, rel=1e-15)
    assert rmse(np.array([2.0])) == 2.0


def test_mean_ci_hand_computation() -> None:
    x = [1.0, 2.0, 4.0, 7.0, 11.0]
    # mean 25 / 5 = 5; deviations -4 -3 -1 2 6; sum of squares 16+9+1+4+36 = 66;
    # s^2 = 66 / 4 = 16.5; half-width = t_{0.975, 4} s / sqrt(5) = 2.776 * sqrt(16.5 / 5)
    ci = mean_ci(x)
    assert ci.mean == 5.0
    assert ci.n == 5
    assert ci.half_width == pytest.approx(2.776 * math.sqrt(16.5 / 5.0), rel=2e-4)
    assert ci.low == pytest.approx(5.0 - ci.half_width)
    assert ci.high == pytest.approx(5.0 + ci.half_width)
    # 90 %: t_{0.95, 4} = 2.132
    assert mean_ci(x, 0.90).half_width == pytest.approx(2.132 * math.sqrt(3.3), rel=2e-4)


def test_mean_ci_of_a_single_value_has_no_width() -> None:
    ci = mean_ci([0.25])
    assert ci.mean == 0.25 and ci.n == 1 and math.isnan(ci.half_width)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: t_quantile(1.0, 3), "p: expected a probability in (0, 1), got 1.0"),
        (lambda: t_quantile(0.0, 3), "p: expected a probability in (0, 1), got 0.0"),
        (lambda: t_quantile(0.9, 0), "df: expected an integer >= 1, got 0"),
        (lambda: t_quantile(0.9, 2.5), "df: expected an integer >= 1, got 2.5"),
        (lambda: rmse([]), "errors: expected at least one value, got none"),
        (lambda: rmse([1.0, float("nan")]), "errors: value 1 is not finite (nan)"),
        (
            lambda: rmse([[1.0, 2.0]]),
            "errors: expected a 1-D sequence of numbers, got shape (1, 2)",
        ),
        (lambda: mean_ci([1.0, 2.0], 1.5), "confidence: expected a number in (0, 1), got 1.5"),
        (lambda: mean_ci([1.0, float("inf")]), "values: value 1 is not finite (inf)"),
    ],
)
def test_bad_input_is_named(call, message: str) -> None:
    with pytest.raises(InputError) as info:
        call()
    assert str(info.value) == message
