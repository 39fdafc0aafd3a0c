"""The one table of estimation methods, and the choice sets of their options.

Every method the command line, the pipeline, the Monte Carlo runner, the
experiments and the figures know is one :class:`Method` record of
:data:`METHODS` (in table order): its name, its title in tables and legends,
the front end's pose solver it reads (the tightly coupled methods read its
pixels, and its H_d / H_c as initial values), whether ``hvo-graph estimate --method``
offers it, which :class:`EstimatorOptions` apply, its plot style and its
factory. The Kalman R_k presets and the smoother's robust losses are defined
here too, once.

The factories import the estimator modules when called: the command line reads
its choices from this table, and ``hvo-graph --help`` should not load GTSAM.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING

from hvo_graph.errors import InputError
from hvo_graph.estimators.choices import DEFAULT_LAG as DEFAULT_LAG
from hvo_graph.estimators.choices import KALMAN_R_PRESETS as KALMAN_R_PRESETS
from hvo_graph.estimators.choices import MOTION_MODEL_CHOICES as MOTION_MODEL_CHOICES
from hvo_graph.estimators.choices import ROBUST_LOSSES as ROBUST_LOSSES
from hvo_graph.estimators.choices import SOLVERS as SOLVERS
from hvo_graph.estimators.choices import VELOCITY_FACTOR_POLICIES as VELOCITY_FACTOR_POLICIES

if TYPE_CHECKING:
    from hvo_graph.estimators.base import Estimator


@dataclass(frozen=True)
class EstimatorOptions:
    """The options of :func:`build_estimator`; each method reads those it lists.

    Attributes:
        seed: random initial state of the Kalman filters; None for unseeded.
        kalman_r: R_k preset of "kalman" (one of :data:`KALMAN_R_PRESETS`).
        kalman_world_velocity: "kalman" rotates measured v into the world frame.
        lag: window of "fixed-lag", seconds.
        robust: None or one of :data:`ROBUST_LOSSES`, on the smoothers' measurements.
        robust_threshold: the robust loss's threshold on the whitened residual
            (None: the smoother's default).
        covariance: also return per-frame covariances (smoothers: marginals).
        acceleration_sigma: the motion model's white-noise acceleration (s_w, s_v),
            one number for both, or "auto" (fitted to the sequence).
        shared_reference_noise: the smoothers keep the reference frame's shared
            pixel noise out of the H_d factors and in the marginals.
        velocity_factors: "gaps" or "all" (:data:`VELOCITY_FACTOR_POLICIES`).
        motion_model: the smoother's motion model, "auto", "wna" or "wnj"
            (:data:`MOTION_MODEL_CHOICES`).
        relinearize_threshold: ISAM2's pose relinearization threshold (None: default).
        relinearize_skip: ISAM2 checks relinearization every this many updates
            (None: default).
    """

    seed: int | None = 0
    kalman_r: str = "paper-noisy"
    kalman_world_velocity: bool = False
    lag: float = DEFAULT_LAG
    robust: str | None = None
    robust_threshold: float | None = None
    covariance: bool = False
    acceleration_sigma: float | tuple[float, float] | str = "auto"
    shared_reference_noise: bool = True
    velocity_factors: str = "gaps"
    motion_model: str = "wna"
    relinearize_threshold: float | None = None
    relinearize_skip: int | None = None


@dataclass(frozen=True)
class Method:
    """One estimation method.

    Attributes:
        name: the label (``--method``, table keys, file names).
        title: human-readable name in tables and legends.
        pose_solver: the front end's pose solver it reads ("homography": H_d; "ippe").
        command: its place among the ``hvo-graph estimate --method`` choices (0 is
            the default), None when the command does not offer it.
        options: the :class:`EstimatorOptions` fields it reads, and "online" when
            its online (causal) estimates differ from its final ones.
        style: ``Axes.plot`` keyword arguments (color, linestyle, marker).
        build: its factory, None for "smoother-online", read from the run of
            ``online_of``.
        solver: the back end of the graph methods
            (:class:`~hvo_graph.estimators.smoother.FactorGraphSmoother`,
            :class:`~hvo_graph.estimators.tight.TightSmoother`).
        online_of: the method whose online (causal) estimates this one is.
    """

    name: str
    title: str
    pose_solver: str
    command: int | None
    options: tuple[str, ...]
    style: Mapping[str, str]
    build: Callable[[Method, EstimatorOptions], Estimator] | None = field(default=None, repr=False)
    solver: str | None = None
    online_of: str | None = None


def _raw(method: Method, options: EstimatorOptions) -> Estimator:
    from hvo_graph.estimators.measurements import RawMeasurements

    return RawMeasurements(velocity_from="poses" if method.pose_solver == "ippe" else "flow")


def _kalman(method: Method, options: EstimatorOptions) -> Estimator:
    from hvo_graph.estimators.kalman import KalmanBaseline

    sigma = options.acceleration_sigma
    return KalmanBaseline(
        r_preset=options.kalman_r,
        # The paper's filter keeps the paper's Q_k unless told otherwise.
        process_noise=None if sigma == "auto" else _kalman_q(sigma),
        seed=options.seed,
        world_frame_velocity=options.kalman_world_velocity,
    )


def _kalman_q(sigma: object) -> object:
    from hvo_graph.estimators.process_noise import acceleration_sigma, kalman_process_noise

    return kalman_process_noise(acceleration_sigma(sigma))  # type: ignore[arg-type]


def _kalman_measured(method: Method, options: EstimatorOptions) -> Estimator:
    """The paper's filter given what the smoother is given: R_k from the front end's
    covariances, the process noise fitted to the sequence, and world-frame velocity
    integration."""
    from hvo_graph.estimators.kalman import KalmanBaseline

    return KalmanBaseline(
        r_preset="measured",
        process_noise="auto",
        velocity_updates="gaps",
        seed=options.seed,
        world_frame_velocity=True,
    )


def _graph(method: Method, options: EstimatorOptions) -> Estimator:
    from hvo_graph.estimators.smoother import FactorGraphSmoother

    isam2 = {
        name: value
        for name in ("relinearize_threshold", "relinearize_skip")
        if (value := getattr(options, name)) is not None
    }
    return FactorGraphSmoother(
        solver=str(method.solver),
        lag=options.lag,
        acceleration_sigma=options.acceleration_sigma,
        shared_reference_noise=options.shared_reference_noise,
        velocity_factors=options.velocity_factors,
        motion_model=options.motion_model,
        robust=options.robust,
        robust_threshold=options.robust_threshold,
        compute_covariance=options.covariance,
        **isam2,  # type: ignore[arg-type]
    )


def _tight(method: Method, options: EstimatorOptions) -> Estimator:
    from hvo_graph.estimators.tight import TightSmoother

    isam2 = {
        name: value
        for name in ("relinearize_threshold", "relinearize_skip")
        if (value := getattr(options, name)) is not None
    }
    return TightSmoother(
        solver=str(method.solver),
        lag=options.lag,
        acceleration_sigma=options.acceleration_sigma,
        robust_threshold=options.robust_threshold,
        compute_covariance=options.covariance,
        **isam2,  # type: ignore[arg-type]
    )


_KALMAN = ("seed", "kalman_r", "kalman_world_velocity", "covariance", "acceleration_sigma")
_GRAPH = (
    "robust",
    "robust_threshold",
    "covariance",
    "acceleration_sigma",
    "shared_reference_noise",
    "velocity_factors",
    "motion_model",
    "online",
)
_ISAM2 = ("relinearize_threshold", "relinearize_skip")
_TIGHT = ("robust_threshold", "covariance", "acceleration_sigma", "online")

#: Every method, in table order.
METHODS: tuple[Method, ...] = (
    Method(
        "measurements",
        "raw measurements (H_d, H_c)",
        "homography",
        4,
        (),
        {"color": "#999999", "linestyle": "-", "marker": "x"},
        _raw,
    ),
    Method(
        "kalman",
        "Kalman (paper, noisy R)",
        "homography",
        3,
        _KALMAN,
        {"color": "#D55E00", "linestyle": "-", "marker": "s"},
        _kalman,
    ),
    Method(
        "kalman-measured",
        "Kalman (measured R)",
        "homography",
        None,
        ("seed", "covariance"),
        {"color": "#E69F00", "linestyle": "-.", "marker": "D"},
        _kalman_measured,
    ),
    Method(
        "smoother",
        "ISAM2 smoothed",
        "homography",
        0,
        (*_GRAPH, *_ISAM2),
        {"color": "#0072B2", "linestyle": "-", "marker": "o"},
        _graph,
        solver="isam2",
    ),
    Method(
        "smoother-online",
        "ISAM2 online",
        "homography",
        None,
        (*_GRAPH, *_ISAM2),
        {"color": "#56B4E9", "linestyle": "-", "marker": "^"},
        online_of="smoother",
    ),
    Method(
        "batch",
        "batch LM",
        "homography",
        1,
        _GRAPH,
        {"color": "#009E73", "linestyle": "--", "marker": "v"},
        _graph,
        solver="batch",
    ),
    Method(
        "fixed-lag",
        "fixed-lag (1 s)",
        "homography",
        2,
        ("lag", *_GRAPH, *_ISAM2),
        {"color": "#CC79A7", "linestyle": ":", "marker": "P"},
        _graph,
        solver="fixed-lag",
    ),
    Method(
        "ippe",
        "IPPE per frame",
        "ippe",
        5,
        (),
        {"color": "#000000", "linestyle": "-", "marker": "*"},
        _raw,
    ),
    Method(
        "tight",
        "tight ISAM2 smoothed",
        "homography",
        6,
        (*_TIGHT, *_ISAM2),
        {"color": "#882255", "linestyle": "-", "marker": "h"},
        _tight,
        solver="isam2",
    ),
    Method(
        "tight-online",
        "tight ISAM2 online",
        "homography",
        None,
        (*_TIGHT, *_ISAM2),
        {"color": "#AA4499", "linestyle": "-", "marker": "<"},
        online_of="tight",
    ),
    Method(
        "tight-batch",
        "tight batch LM",
        "homography",
        7,
        _TIGHT,
        {"color": "#332288", "linestyle": "--", "marker": ">"},
        _tight,
        solver="batch",
    ),
    Method(
        "tight-fixed-lag",
        "tight fixed-lag (1 s)",
        "homography",
        8,
        ("lag", *_TIGHT, *_ISAM2),
        {"color": "#44AA99", "linestyle": ":", "marker": "d"},
        _tight,
        solver="fixed-lag",
    ),
)

#: {name: Method}.
BY_NAME: Mapping[str, Method] = MappingProxyType({m.name: m for m in METHODS})

#: Every method's name, in table order.
METHOD_LABELS: tuple[str, ...] = tuple(BY_NAME)

#: {name: title}.
METHOD_TITLES: Mapping[str, str] = MappingProxyType({m.name: m.title for m in METHODS})

#: The ``hvo-graph estimate --method`` choices; the first is the default.
COMMAND_METHODS: tuple[str, ...] = tuple(
    m.name for m in sorted((m for m in METHODS if m.command is not None), key=lambda m: m.command)
)


def method(name: str) -> Method:
    """The :class:`Method` called ``name``, or InputError listing the choices."""
    found = BY_NAME.get(name)
    if found is None:
        raise InputError(f"method: expected one of {', '.join(METHOD_LABELS)}, got {name!r}")
    return found


def check_methods(methods: Iterable[str]) -> tuple[str, ...]:
    """The method names as a tuple, in the order given.

    Raises:
        InputError: empty, unknown or repeated names.
    """
    if isinstance(methods, str):
        methods = [methods]
    chosen = tuple(methods)
    if not chosen:
        raise InputError(f"methods: expected at least one of {', '.join(METHOD_LABELS)}")
    for label in chosen:
        if label not in BY_NAME:
            raise InputError(
                f"methods: unknown method {label!r}, expected one of {', '.join(METHOD_LABELS)}"
            )
    if len(set(chosen)) != len(chosen):
        dup = next(m for m in chosen if chosen.count(m) > 1)
        raise InputError(f"methods: {dup!r} is listed twice")
    return chosen


#: Every option a method can take: the :class:`EstimatorOptions` fields and "online".
OPTION_NAMES: tuple[str, ...] = (*EstimatorOptions.__dataclass_fields__, "online")


def check_applicable(name: str, given: Iterable[str], *, spell: Callable[[str], str] = str) -> None:
    """InputError when an option in ``given`` does not apply to method ``name``.

    A flag that would be silently ignored is an error: the message names the
    option (as ``spell`` writes it, e.g. "--lag") and the methods it applies to.
    """
    record = method(name)
    for option in given:
        if option not in OPTION_NAMES:
            raise InputError(
                f"{spell(option)}: unknown option, expected one of "
                f"{', '.join(spell(o) for o in OPTION_NAMES)}"
            )
        if option not in record.options:
            users = [m for m in COMMAND_METHODS if option in BY_NAME[m].options]
            raise InputError(
                f"{spell(option)}: does not apply to method {name!r} "
                f"(it applies to {', '.join(users) or 'no method'})"
            )


def build_estimator(name: str, options: EstimatorOptions | None = None) -> Estimator:
    """A fresh estimator of method ``name`` with ``options`` (defaults when None).

    Raises:
        InputError: an unknown name, or a method read from another one's run
            (``online_of``: build that one and take its ``online_trajectory()``).
    """
    record = method(name)
    if record.build is None:
        raise InputError(
            f"method {name!r}: no estimator of its own; it is the online estimate of "
            f"{record.online_of!r}"
        )
    return record.build(record, options or EstimatorOptions())
