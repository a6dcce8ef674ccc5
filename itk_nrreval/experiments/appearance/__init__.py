"""The appearance-model diagnostics of the paper's Table 1: the full appearance model and its
Voronoi cell populations (:mod:`~itk_nrreval.experiments.appearance.model`), and their run
over a manifest's registrations as ``nrreval diagnose`` writes it
(:mod:`~itk_nrreval.experiments.appearance.diagnose`).
"""

__all__: list[str] = []
