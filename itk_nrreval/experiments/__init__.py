"""The paper's experiments built on the measures: the perturbation experiment
(:mod:`~itk_nrreval.experiments.perturbation`, clamped-plate-spline warps), parameter sweeps,
the appearance-model diagnostics, the registration engines, the demo and the true
correspondence error that the benchmarks use as ground truth.
"""

__all__: list[str] = []
