"""The paper's measures as pure numerics on numpy arrays: the texture model, specificity and
generalization with the nearest-training search behind them, overlap, confidence intervals,
the verdict, label metrics and per-subject quality control.

No module here imports SimpleITK, ITK, nibabel or matplotlib; images given as files or ITK
objects reach these measures through :mod:`itk_nrreval.io`.
"""

__all__: list[str] = []
