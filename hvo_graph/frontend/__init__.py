"""The front end: images -> feature tracks -> per-frame H_d pose and H_c twist measurements.

- :mod:`~hvo_graph.frontend.tracking`: the OpenCV KLT tracker (images -> tracks);
- :mod:`~hvo_graph.frontend.measure`: tracks -> pose from the discrete homography H_d
  and twist from the continuous homography H_c, with covariances.

Every public name of both modules is re-exported here and imported on first use
(``from hvo_graph.frontend import measure_sequence``).
"""

from hvo_graph import _lazy_exports

__all__, __getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "hvo_graph.frontend.tracking": (
            "TrackerConfig",
            "FeatureTracker",
            "track_images",
            "tracks_from_images",
        ),
        "hvo_graph.frontend.measure": (
            "DEFAULT_PIXEL_SIGMA",
            "MIN_PIXEL_SIGMA",
            "POSE_SOLVERS",
            "FrontEndConfig",
            "MeasurementFrontEnd",
            "measure_sequence",
        ),
    },
)
