"""itk-nrreval: which registration of a group of images is best, without ground truth.

Twining et al., "Evaluating Registration Without Ground Truth", IEEE TMI. The registered
images of a group give a shape-free texture model; its specificity scores the registration
(lower is better). Where labels exist, the generalized Tanimoto overlap is the reference.
"""

from ._errors import EngineError, InputError
from ._pipeline import Coverage
from ._version import __version__
from .evaluation import (
    Confidence,
    Decision,
    EvaluationResult,
    Execution,
    OpenPair,
    RegistrationScores,
    ResampledImages,
    Resampling,
    Verdict,
    evaluate,
    export_resampled,
    ranks,
    relative_ranks,
)
from .experiments.appearance.diagnose import DiagnosticsResult, diagnose
from .experiments.appearance.model import (
    AppearanceDiagnostics,
    CellPopulations,
    appearance_diagnostics,
)
from .experiments.perturbation import ValidationResult, ValidationRow, ValidationSummary, validate
from .experiments.registration import RegistrationResult, register
from .experiments.warps import (
    ClampedPlateSpline,
    CPSWarp,
    cps_warp,
    max_safe_displacement,
    random_cps,
    warp_stack,
)
from .io._images import Geometry
from .io.frame import FrameMapping
from .io.manifest import (
    Manifest,
    ManifestRegistration,
    add_registration,
    load_manifest,
    write_manifest,
)
from .io.pipeline_outputs import manifest_from_derivatives, manifest_from_transforms
from .io.plausibility import Plausibility, SubjectThresholds, Thresholds, deformation_plausibility
from .measures.confidence import Comparison, Interval, RankStability
from .measures.description_length import DescriptionLength
from .measures.label_metrics import LabelMetrics, MetricSummary
from .measures.model import MixtureModel, TextureModel
from .measures.overlap import WEIGHTINGS, OverlapTable, generalized_overlap, overlap_table
from .measures.specificity import (
    GeneralizationResult,
    MixtureSummary,
    SpecificityComparison,
    SpecificityResult,
    compare_specificity,
    generalization,
    loo_generalization,
    specificity,
    texture_measures,
)
from .measures.subject_qc import SubjectQC

__all__ = [
    "appearance_diagnostics",
    "AppearanceDiagnostics",
    "CellPopulations",
    "diagnose",
    "DiagnosticsResult",
    "cps_warp",
    "max_safe_displacement",
    "random_cps",
    "warp_stack",
    "ClampedPlateSpline",
    "CPSWarp",
    "validate",
    "ValidationResult",
    "ValidationRow",
    "ValidationSummary",
    "InputError",
    "EngineError",
    "TextureModel",
    "MixtureModel",
    "Geometry",
    "register",
    "RegistrationResult",
    "SpecificityResult",
    "MixtureSummary",
    "GeneralizationResult",
    "SpecificityComparison",
    "specificity",
    "generalization",
    "texture_measures",
    "compare_specificity",
    "loo_generalization",
    "Manifest",
    "ManifestRegistration",
    "load_manifest",
    "write_manifest",
    "add_registration",
    "manifest_from_derivatives",
    "manifest_from_transforms",
    "EvaluationResult",
    "RegistrationScores",
    "Interval",
    "Comparison",
    "RankStability",
    "FrameMapping",
    "Coverage",
    "SubjectQC",
    "LabelMetrics",
    "DescriptionLength",
    "MetricSummary",
    "Verdict",
    "Decision",
    "OpenPair",
    "Plausibility",
    "Thresholds",
    "SubjectThresholds",
    "deformation_plausibility",
    "evaluate",
    "export_resampled",
    "ResampledImages",
    "Resampling",
    "Confidence",
    "Execution",
    "ranks",
    "relative_ranks",
    "WEIGHTINGS",
    "OverlapTable",
    "overlap_table",
    "generalized_overlap",
    "__version__",
]
