"""Correspondence: unlabelled marker detections from many cameras -> named markers, the step before every estimator.

``associate_session(folder)`` is the entry point (batgraph.associate.session); the stages are the detections'
input (.detections), cross-view matching per frame (.views), tracking the seeded markers through time (.tracks,
with .segments and .assignment), naming every detection by where its marker is (.refine), cameras out of step on
some frames (.jitter), the whole on arrays (.core), and test scenes with their scoring (.scenes, .score).
"""

from .core import AssociateOptions
from .session import (
    Figures,
    associate_session,
    check_out,
    require_named,
    warning_texts,
    write_associated,
    write_observations,
)

__all__ = ["AssociateOptions", "Figures", "associate_session", "check_out", "require_named", "warning_texts",
           "write_associated", "write_observations"]
