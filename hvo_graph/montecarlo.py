"""Monte Carlo runs: one simulated seed through every method, and many seeds in parallel.

The library side of ``experiments/compare.py``, ``sweep.py`` and ``images.py``.
One seed of one scenario (:class:`~hvo_graph.sim.scenario.ScenarioConfig`) is
simulated once and measured once per front-end pose solver: the homography front
end (H_d poses, H_c twists) feeds every method except "ippe", which gets OpenCV's
per-frame ``solvePnP(SOLVEPNP_IPPE)`` poses. Every random source is seeded from
the config's seed (pixel noise, layout of extra points, the Kalman filter's
random initial state), so the same seed gives the same numbers.

The methods are the rows of :data:`hvo_graph.estimators.registry.METHODS`;
"smoother-online" is the same ISAM2 run as "smoother", each frame's estimate
right after its own update (``Estimator.online_trajectory``), no second run.
Then errors against the ground truth per seed, and their aggregation over seeds.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, wait
from dataclasses import dataclass, field

import numpy as np

from hvo_graph.errors import InputError, as_number
from hvo_graph.estimators.base import Estimator
from hvo_graph.estimators.noise_estimation import estimate_process_noise
from hvo_graph.estimators.process_noise import DEFAULT_ACCELERATION_SIGMA
from hvo_graph.estimators.registry import (
    METHOD_LABELS,
    EstimatorOptions,
    build_estimator,
    check_methods,
    method,
)
from hvo_graph.eval.bounds import BOUND, posterior_bound
from hvo_graph.eval.consistency import trajectory_nees
from hvo_graph.eval.metrics import QUANTITIES, ErrorSeries, ErrorSummary, error_series, summarize
from hvo_graph.eval.stats import MeanCI, mean_ci
from hvo_graph.parallel import (  # WORKER_ENVIRONMENT: also read from here, its old home
    WORKER_ENVIRONMENT,  # noqa: F401
    check_scheduler,
    executor,
    resolve_workers,
)
from hvo_graph.pipeline import measure
from hvo_graph.report.progress import ProgressBar
from hvo_graph.sim.families import draw
from hvo_graph.sim.scenario import Scenario, ScenarioConfig, simulate
from hvo_graph.types import FrameMeasurement, Trajectory

#: Window of the fixed-lag smoother in the experiments, seconds.
FIXED_LAG_SECONDS = 1.0
_NAMES = tuple(q.name for q in QUANTITIES)


def make_method(label: str, seed: int, *, covariance: bool = False) -> Estimator:
    """A fresh estimator for ``label`` as the experiments run it (Kalman seed ``seed``,
    :data:`FIXED_LAG_SECONDS`, smoother covariances if asked); not for
    "smoother-online", which reads a "smoother" run."""
    options = EstimatorOptions(seed=seed, lag=FIXED_LAG_SECONDS, covariance=covariance)
    return build_estimator(label, options)


class MethodRuns:
    """The methods on one sequence, each estimator run once.

    Measurements are made once per front-end pose solver (``measure``); a method
    read from another one's run (``online_of``) takes that run's online estimates.

    Args:
        measure: the measurements for a pose solver ("homography" or "ippe").
        seed: seed of the Kalman filters' random initial state.
        covariance: the smoothers also return their marginal covariances.
        methods: every label that will be asked for (None: not known); a run not read
            for online estimates skips what serves them alone (``Estimator.run``).
    """

    def __init__(
        self,
        measure: Callable[[str], Sequence[FrameMeasurement]],
        seed: int,
        *,
        covariance: bool = False,
        methods: Sequence[str] | None = None,
    ) -> None:
        self._measure = measure
        self._read_online = (
            None if methods is None else {method(m).online_of for m in methods} - {None}
        )
        self.seed = seed
        self.covariance = covariance
        self._frames: dict[str, Sequence[FrameMeasurement]] = {}
        self._runs: dict[str, tuple[Estimator, Trajectory]] = {}

    def frames(self, pose_solver: str) -> Sequence[FrameMeasurement]:
        """The measurements of ``pose_solver``, made on first use."""
        if pose_solver not in self._frames:
            self._frames[pose_solver] = self._measure(pose_solver)
        return self._frames[pose_solver]

    def trajectory(self, label: str) -> Trajectory:
        """The final trajectory of method ``label`` (online estimates for ``online_of``)."""
        record = method(label)
        source = method(record.online_of) if record.online_of else record
        if source.name not in self._runs:
            frames = self.frames(source.pose_solver)
            estimator = make_method(source.name, self.seed, covariance=self.covariance)
            online = self._read_online is None or source.name in self._read_online
            self._runs[source.name] = (estimator, estimator.run(frames, online=online))
        estimator, final = self._runs[source.name]
        return estimator.online_trajectory() if record.online_of else final

    def estimator(self, label: str) -> Estimator | None:
        """The estimator that ran method ``label`` (None if it has not run)."""
        run = self._runs.get(label)
        return None if run is None else run[0]


@dataclass
class SeedResult:
    """Errors of every method on one simulated seed.

    Attributes:
        seed: the scenario's seed.
        config: the scenario.
        summaries: per method, RMSE and max after ``skip`` seconds.
        series: per method, per-frame errors over the whole sequence (empty when
            not kept).
        skip: seconds left out at the start of the summaries.
        nees: per method with covariances, (pose, twist) mean NEES per degree of
            freedom after ``skip`` seconds (:func:`~hvo_graph.eval.consistency.trajectory_nees`).
        family: the scenario family of a randomised draw ("" for a plain config).
    """

    seed: int
    config: ScenarioConfig
    summaries: dict[str, ErrorSummary]
    series: dict[str, ErrorSeries] = field(default_factory=dict)
    skip: float = 1.0
    nees: dict[str, tuple[float, float]] = field(default_factory=dict)
    family: str = ""


def _checked_skip(skip: float, duration: float) -> float:
    """``skip`` seconds, >= 0 and leaving part of a ``duration`` s sequence to evaluate."""
    skip = as_number(skip, "skip", at_least=0.0, what="a number of seconds")
    if skip >= duration:
        raise InputError(
            f"skip: {skip:g} s leaves no frame of a {duration:g} s sequence to evaluate"
        )
    return skip


def run_seed(
    config: ScenarioConfig,
    methods: Sequence[str] = METHOD_LABELS,
    *,
    skip: float = 1.0,
    keep_series: bool = True,
    bound: bool = False,
) -> SeedResult:
    """Simulate ``config`` once and run every method on it.

    Args:
        config: the scenario, with its seed.
        methods: names from :data:`~hvo_graph.estimators.registry.METHOD_LABELS`.
        skip: errors are summarized over frames with t >= t_0 + skip (seconds),
            after the estimators' start-up transient (the Kalman filter starts
            from a random state).
        keep_series: also return the per-frame errors.
        bound: also the pose's posterior Cramér-Rao bound, under :data:`BOUND`
            (:func:`bound_summary`).
    Raises:
        InputError: bad methods or skip, or an estimator's InputError with the
            seed and method prepended.
        RuntimeError: any other failure of an estimator, naming the seed and method.
    """
    methods = check_methods(methods)
    if not isinstance(config, ScenarioConfig):
        raise InputError(f"config: expected a ScenarioConfig, got {type(config).__name__}")
    skip = _checked_skip(skip, config.duration)
    result = SeedResult(seed=config.seed, config=config, summaries={}, skip=float(skip))
    return _evaluate(simulate(config), result, methods, keep_series, covariance=False, bound=bound)


@dataclass(frozen=True)
class FamilySeed:
    """One randomised draw to run: ``family`` of :mod:`hvo_graph.sim.families`, ``seed``,
    optionally a shorter ``duration`` (seconds)."""

    family: str
    seed: int
    duration: float | None = None


def run_family_seed(
    job: FamilySeed,
    methods: Sequence[str] = METHOD_LABELS,
    *,
    skip: float = 1.0,
    keep_series: bool = False,
    bound: bool = False,
) -> SeedResult:
    """Draw ``job`` (:func:`hvo_graph.sim.families.draw`) and run every method on it, with
    the smoothers' covariances and their NEES (``SeedResult.nees``); as :func:`run_seed`."""
    methods = check_methods(methods)
    drawn = draw(job.family, job.seed, duration=job.duration)
    config = drawn.scenario.config
    skip = _checked_skip(skip, config.duration)
    result = SeedResult(
        seed=job.seed, config=config, summaries={}, skip=float(skip), family=job.family
    )
    return _evaluate(drawn.scenario, result, methods, keep_series, covariance=True, bound=bound)


def _evaluate(
    scenario: Scenario,
    result: SeedResult,
    methods: Sequence[str],
    keep_series: bool,
    *,
    covariance: bool,
    bound: bool = False,
) -> SeedResult:
    """Fill ``result`` with every method's errors (and NEES where covariances exist), and
    the bound if asked, with the process noise the smoother chose on these data."""
    truth = scenario.groundtruth
    t_start = float(truth.t[0]) + result.skip
    runs = MethodRuns(
        lambda solver: measure(
            scenario.observations, scenario, method="ippe" if solver == "ippe" else "smoother"
        ),
        result.seed,
        covariance=covariance,
        methods=methods,
    )
    where = f"{result.family} " if result.family else ""
    for label in methods:
        try:
            trajectory = runs.trajectory(label)
            series = error_series(trajectory, truth)
            result.summaries[label] = summarize(series, t_start=t_start)
            if trajectory.covariances is not None:
                result.nees[label] = trajectory_nees(trajectory, truth, t_start=t_start)
        except InputError as exc:
            raise InputError(f"{where}seed {result.seed}, method {label}: {exc}") from exc
        except Exception as exc:  # e.g. a GTSAM failure: say where, even from a worker process
            raise RuntimeError(
                f"{where}seed {result.seed}, method {label}: {type(exc).__name__}: {exc}"
            ) from exc
        if keep_series:
            result.series[label] = series
    if bound:
        smoother = runs.estimator("smoother")
        # the bound's prior is white-noise acceleration: take the smoother's densities
        # only when they are of that model
        if smoother is not None and getattr(smoother, "motion_model", "wna") == "wna":
            sigma = smoother.acceleration_sigma  # type: ignore[attr-defined]
        else:
            fit = estimate_process_noise(
                runs.frames("homography"), default=DEFAULT_ACCELERATION_SIGMA
            )
            sigma = fit.acceleration_sigma
        result.summaries[BOUND] = bound_summary(scenario, sigma, t_start)
    return result


#: Draws with more plane points than this get no bound (NaN): hundreds of landmarks, as
#: a traverse over a field of points has, take minutes per draw.
BOUND_MAX_POINTS = 100


def bound_summary(
    scenario: Scenario, acceleration_sigma: tuple[float, float], t_start: float
) -> ErrorSummary:
    """The pose's posterior Cramér-Rao bound (:func:`~hvo_graph.eval.bounds.posterior_bound`)
    as an error summary over the frames an estimator is evaluated on: the observed frames
    with t >= ``t_start``. RMSE = sqrt(mean of the bound's traces), max = the largest
    per-frame bound; velocity entries None. Noise-free pixels determine the pose: 0.
    NaN (not computed) beyond :data:`BOUND_MAX_POINTS` plane points."""
    if len(scenario.points_world) > BOUND_MAX_POINTS:
        nan = float("nan")
        return ErrorSummary(nan, nan, nan, nan, None, None, None, None, frames=0)
    pose_bound = posterior_bound(scenario, acceleration_sigma)
    observed = np.array([int(o.index) for o in scenario.observations])
    keep = observed[pose_bound.t[observed] >= t_start]
    position, orientation = pose_bound.position[keep], pose_bound.orientation[keep]
    if scenario.pixel_sigma == 0:  # posterior_bound floors the sigma to stay finite
        position, orientation = np.zeros_like(position), np.zeros_like(orientation)
    return ErrorSummary(
        position_rmse=float(np.sqrt(np.mean(position**2))),
        position_max=float(position.max()),
        orientation_rmse=float(np.sqrt(np.mean(orientation**2))),
        orientation_max=float(orientation.max()),
        linear_velocity_rmse=None,
        linear_velocity_max=None,
        angular_velocity_rmse=None,
        angular_velocity_max=None,
        frames=int(keep.size),
    )


def _run_seed_job(
    job: tuple[ScenarioConfig | FamilySeed, tuple[str, ...], float, bool, bool],
) -> SeedResult:
    config, methods, skip, keep_series, bound = job
    run = run_family_seed if isinstance(config, FamilySeed) else run_seed
    return run(config, methods, skip=skip, keep_series=keep_series, bound=bound)  # type: ignore[arg-type]


def _cost(config: ScenarioConfig | FamilySeed) -> float:
    """Rough cost of a run (front end ~ frames x points); draws are not known before."""
    return config.num_frames * config.num_points if isinstance(config, ScenarioConfig) else 0.0


def run_seeds(
    configs: Sequence[ScenarioConfig | FamilySeed],
    methods: Sequence[str] = METHOD_LABELS,
    *,
    skip: float = 1.0,
    keep_series: bool = True,
    workers: int | None = None,
    progress: bool = True,
    label: str = "seeds",
    scheduler: str | None = None,
    bound: bool = False,
) -> list[SeedResult]:
    """:func:`run_seed` for every config, over ``workers`` processes or a Dask cluster;
    results in input order, and the same numbers wherever they ran (each run is a
    deterministic function of its config).

    Args:
        configs: one scenario per run (typically the same scenario, different seeds),
            or randomised draws (:class:`FamilySeed`, run by :func:`run_family_seed`).
        methods: names from :data:`~hvo_graph.estimators.registry.METHOD_LABELS`.
        skip: seconds left out at the start of every summary.
        keep_series: keep the per-frame errors.
        workers: local processes (``concurrent.futures.ProcessPoolExecutor``, started
            with "spawn" and :data:`~hvo_graph.parallel.WORKER_ENVIRONMENT`); 1 runs in
            this process; None = ``os.cpu_count()``. Not with ``scheduler``.
        progress: draw a :class:`ProgressBar` on stderr.
        label: what the progress bar counts.
        scheduler: address of a running Dask scheduler (``tcp://HOST:PORT``): the seeds
            run on its workers (:func:`hvo_graph.parallel.executor`).
        bound: also each seed's posterior Cramér-Rao bound of the pose (:data:`BOUND`).
    Raises:
        InputError: bad arguments, or no scheduler at ``scheduler``; a seed's failure
            (naming the seed and method) stops the run.
    """
    methods = check_methods(methods)
    scheduler = check_scheduler(scheduler, workers)
    workers = resolve_workers(workers)
    configs = list(configs)
    if not configs:
        raise InputError("configs: expected at least one scenario")
    jobs = [(config, methods, skip, keep_series, bound) for config in configs]
    results: list[SeedResult | None] = [None] * len(jobs)
    with ProgressBar(len(jobs), label=label, enabled=progress) as bar:
        if scheduler is None and (workers == 1 or len(jobs) == 1):
            for i, job in enumerate(jobs):
                results[i] = _run_seed_job(job)
                bar.update()
        else:
            # Longest runs first (front-end cost ~ frames x points), so that no
            # worker is left with a long run at the end; results keep the input order.
            order = sorted(range(len(jobs)), key=lambda i: -_cost(configs[i]))
            with executor(min(workers, len(jobs)), scheduler) as pool:
                pending = {pool.submit(_run_seed_job, jobs[i]): i for i in order}
                while pending:
                    finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for future in finished:
                        i = pending.pop(future)
                        error = future.exception()
                        if error is not None:
                            for other in pending:
                                other.cancel()
                            raise error
                        results[i] = future.result()
                        bar.update()
    return [r for r in results if r is not None]


# -- aggregation over seeds --------------------------------------------------------------


def metric_values(
    results: Sequence[SeedResult], method: str, quantity: str, stat: str = "rmse"
) -> np.ndarray:
    """(S,) the ``stat`` ("rmse" or "max") of ``quantity`` for ``method``, one per seed.

    NaN where a seed gave no value (velocity unknown).
    """
    if stat not in ("rmse", "max"):
        raise InputError(f"stat: expected 'rmse' or 'max', got {stat!r}")
    if quantity not in {q.name for q in QUANTITIES}:
        names = ", ".join(q.name for q in QUANTITIES)
        raise InputError(f"quantity: expected one of {names}, got {quantity!r}")
    out = np.empty(len(results))
    for i, r in enumerate(results):
        if method not in r.summaries:
            raise InputError(f"seed {r.seed}: no result for method {method!r}")
        value = getattr(r.summaries[method], f"{quantity}_{stat}")
        out[i] = np.nan if value is None else value
    return out


def _finite_ci(values: np.ndarray) -> MeanCI | None:
    finite = values[np.isfinite(values)]
    return mean_ci(finite) if finite.size else None


def method_statistics(
    results: Sequence[SeedResult], method: str, stat: str = "rmse"
) -> dict[str, MeanCI | None]:
    """Per quantity, the mean over seeds of ``stat`` with its 95 % CI (None: no values)."""
    return {q: _finite_ci(metric_values(results, method, q, stat)) for q in _NAMES}


def ratio_statistics(
    results: Sequence[SeedResult], numerator: str, denominator: str
) -> dict[str, MeanCI | None]:
    """Per quantity, the mean over seeds of RMSE(numerator) / RMSE(denominator), 95 % CI.

    The ratio is taken per seed first (a paired comparison on identical data),
    then averaged: the mean of per-seed ratios, not the ratio of mean RMSEs.
    """
    out: dict[str, MeanCI | None] = {}
    for q in _NAMES:
        num = metric_values(results, numerator, q)
        den = metric_values(results, denominator, q)
        with np.errstate(divide="ignore", invalid="ignore"):
            out[q] = _finite_ci(num / den)
    return out


def mean_error_over_time(
    results: Sequence[SeedResult], method: str
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Per-frame error of ``method`` averaged over seeds.

    Returns:
        t (K,) seconds and, per quantity, (K,) mean error (NaN where no seed has a value).
    Raises:
        InputError: series not kept, or seeds with different frame times.
    """
    if not results or any(method not in r.series for r in results):
        raise InputError(f"mean_error_over_time: per-frame errors of {method!r} were not kept")
    t = results[0].series[method].t
    curves: dict[str, np.ndarray] = {}
    for q in _NAMES:
        rows = []
        for r in results:
            s = r.series[method]
            if len(s.t) != len(t) or not np.allclose(s.t, t):
                raise InputError(f"seed {r.seed}: frame times differ from seed {results[0].seed}")
            e = getattr(s, q)
            rows.append(np.full(len(t), np.nan) if e is None else np.asarray(e, dtype=float))
        stack = np.array(rows)
        count = np.isfinite(stack).sum(axis=0)
        total = np.where(np.isfinite(stack), stack, 0.0).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            curves[q] = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return np.asarray(t, dtype=float), curves
