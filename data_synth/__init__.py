"""Synthetic brain-like image populations with known true correspondence.

``make_population(kind="phantom" | "mni", dim=2 | 3, n=36, seed=0)`` returns a template and N
subjects, each with its image, label map and true ITK transforms to and from the template
frame; ``perfect_registration`` resamples every subject into the template frame through them
(``perfectly_registered_arrays``: the same as numpy arrays, the set ``nrreval validate``
perturbs).
``contrasts=("t1", "t2")`` images every subject in a second, T2-like contrast of the same
anatomy (a two-modality population with known correspondence).
See :mod:`data_synth.population` for the transform conventions.
"""

from .mni import MNI_LABELS, make_mni
from .phantom import CONTRASTS, PHANTOM_LABELS, Phantom, make_phantom
from .population import (
    PerfectRegistration,
    Population,
    Subject,
    make_population,
    perfect_registration,
    perfectly_registered_arrays,
    velocity_exponential,
)
from .writing import write_population

__all__ = [
    "CONTRASTS",
    "MNI_LABELS",
    "PHANTOM_LABELS",
    "Phantom",
    "Subject",
    "Population",
    "PerfectRegistration",
    "make_population",
    "make_phantom",
    "make_mni",
    "perfect_registration",
    "perfectly_registered_arrays",
    "velocity_exponential",
    "write_population",
]
