"""The verdict: which registrations the evidence decides are better than which, and why.

Specificity, like any intensity-based measure, can be lowered by a registration that fits
what it should not: noise, bias, structure that does not correspond. Rougher fields fit
more, so on its own a lower specificity does not say a registration is better (the
known-truth benchmark, ``benchmarks/bench_verdict.py``, measures this: the old verdict,
which trusted every separable specificity difference and ranked every flagged registration
last, decided 16 of 90 pairs against the truth). The verdict therefore decides a pair only
on evidence that holds up. A measure's separable preference (the subject-level 95%
interval of the difference excludes 0) for ``a`` over ``b`` is **evidence** unless

- ``a``'s fields are rougher by ``dr = SDlogJ(a) - SDlogJ(b)`` (the mean standard
  deviation of the log Jacobian determinant) and the advantage is smaller than roughness
  alone can buy: ``ln(spec(b) / spec(a)) < EXCHANGE_RATE * dr`` for specificity (a 1.7x
  lower specificity for 0.1 rougher fields, 4x for 0.25), and on the log-odds of the
  inverse-volume generalized overlap with :data:`OVERLAP_EXCHANGE_RATE`
  (:data:`OVERLAP_RATE_AGAINST_LINEAR` where ``b`` does not deform locally, an affine
  registration: there SDlogJ is all of ``a``'s local deformation, the correspondence it
  gains included); smoother fields are not charged; or
- it is the overlap's preference for a registration flagged as implausible (overlap is what
  a label-matching cheat games, by folding: Rohlfing's cheat); or
- it is a preference for ``a`` over a ``b`` that folds (at least
  :data:`NO_FOLDING_FRACTION` of its voxels, and more than ``a``), by less than
  ``exp(EXCHANGE_RATE * SDlogJ(a))`` in specificity or ``exp(OVERLAP_EXCHANGE_RATE *
  SDlogJ(a))`` in the overlap's odds: ``b``'s SDlogJ, inflated by the near-zero
  determinants around its folds, does not say which fields are the rougher, so ``a`` is
  charged as if ``b``'s were flat (a 25 mm B-spline folding 2.3% of its voxels, SDlogJ
  0.54, corresponded better than demons at 1 mm, SDlogJ 0.29, whose specificity was
  separably lower: issue 41's held-out case; in the benchmark's ``FRESH5`` a 3D B-spline
  folding 1.7% corresponded better than demons at 2 mm, whose specificity and overlap
  were separably better); or
- it is specificity's preference by less than :data:`MIN_SPECIFICITY_RATIO` (1.2x) for a
  registration whose fields are not smoother by at least :data:`MIN_ROUGHNESS_DIFFERENCE`.

The charge has a converse, for specificity only (:data:`SMOOTHNESS_RATE`): when ``a``'s
fields are rougher by ``dr`` (at least :data:`MIN_ROUGHNESS_DIFFERENCE`) and its
specificity advantage, even at the top of its subject-level interval, is below
``exp(SMOOTHNESS_RATE * dr)``, that is specificity's evidence for the smoother ``b``, if
``b`` deforms locally (its subjects' median non-linear displacement is at least
:data:`~itk_nrreval.measures.subject_qc.IDENTITY_MM`; an affine registration's zero SDlogJ says
nothing of the deformation it leaves out), folds no more than ``a`` and less than
:data:`NO_FOLDING_FRACTION` (folds are roughness that SDlogJ, taken over the voxels that
do not fold, ranks poorly: 3D B-splines folding 3-6% had a lower SDlogJ than demons that
corresponded better; in ``FRESH6`` a 25 mm B-spline folding 4.4% was preferred over a
10 mm one folding 8.6% that corresponded better): the
extra roughness bought too little to be correspondence (the flat end of the trade-off's
L-curve: demons or B-splines past their knee, fitting noise). Between the two rates the
pair is the knee, and stays open unless the overlap decides it. This converse counts only
between two registrations of one known family (``family``: the same ``method`` and
``engine`` in the manifest's ``parameters``): how rough a registration's fields are for the
correspondence they reach is a property of its method, so across families (or where a
family is unknown) the open pair's reason says which way it leans, and nothing is decided.

A pair is decided for ``a`` when there is evidence for ``a`` and none for ``b`` (with
labels, specificity and overlap each count; a preference that is not evidence does not
count against the other measure either: on the benchmark's demons sweeps the rough fields'
lower specificity is such a preference, and the overlap's evidence for the smoother setting
was right every time). Besides, **severe folding** decides: a registration that folds at
least :data:`SEVERE_FOLDED_FRACTION` of its voxels (a tear, not a fold) is decided worse
than every registration that folds less than :data:`NO_FOLDING_FRACTION`.

**The description length** (:mod:`~itk_nrreval.measures.description_length`, where
``evaluate(description_length=True)`` computed it) is a third measure: its preference by at
least :data:`~itk_nrreval.measures.description_length.MIN_Z` jackknife standard errors is
evidence, like specificity's and the overlap's, but only between two registrations of one
family (the same ``method`` and ``engine`` in the manifest's ``parameters``: settings of
one method, as a sweep makes). No roughness charge applies: its shape part prices the
deformation already. On the known-truth benchmark (``benchmarks/bench_description_length.py``)
it decided no pair wrong within a family on any split, and between families it decided
pairs wrong in both directions (a 40 mm B-spline grid that corresponded better than SyN,
priced above SyN's better texture fit; a 60 mm grid, better than affine, priced below its
shape cost), so there it is no evidence. Within a family it decides what roughness does
not: a setting that under-fits (demons smoothed by 16 mm, a 60 mm grid) against one that
corresponds better.

Anything else stays open, with the reason in words, and so does every pair whose
decisions go round in a cycle (a > b > c > a by different evidence: one of them is
wrong). A plausibility flag by itself decides nothing: on the benchmark a B-spline
registration that folds 2.4% of its voxels had the best true error of its case, and
"flagged after every unflagged registration" decided it wrong twice.

Below :data:`MIN_SAMPLES` specificity samples the verdict decides nothing: every pair is
open, and the text says that the scores have not converged (a small M stays legal for a
quick try).
"""

from __future__ import annotations

import itertools
import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from ._verdict_thresholds import (  # the rules' numbers, and how each was set
    EXCHANGE_RATE,
    MIN_ROUGHNESS_DIFFERENCE,
    MIN_SAMPLES,
    MIN_SPECIFICITY_RATIO,
    NO_FOLDING_FRACTION,
    OVERLAP_EXCHANGE_RATE,
    OVERLAP_RATE_AGAINST_LINEAR,
    SEVERE_FOLDED_FRACTION,
    SMOOTHNESS_RATE,
)
from .confidence import Comparison
from .description_length import MIN_Z, z_of_difference

__all__ = [
    "Decision",
    "OpenPair",
    "Verdict",
    "verdict",
    "EXCHANGE_RATE",
    "SMOOTHNESS_RATE",
    "OVERLAP_EXCHANGE_RATE",
    "OVERLAP_RATE_AGAINST_LINEAR",
    "MIN_ROUGHNESS_DIFFERENCE",
    "MIN_SPECIFICITY_RATIO",
    "SEVERE_FOLDED_FRACTION",
    "NO_FOLDING_FRACTION",
    "MIN_SAMPLES",
]

_SPECIFICITY = "specificity"
_OVERLAP = "overlap.inverse_volume"
_DESCRIPTION_LENGTH = "description length"
# in a decision's basis
_WORD = {
    _SPECIFICITY: "specificity",
    _OVERLAP: "overlap",
    _DESCRIPTION_LENGTH: "description length",
}


@dataclass(frozen=True)
class Decision:
    """One ordered pair the verdict asserts: `better` is a better registration than `worse`.

    Attributes
    ----------
    better, worse : str
        Registration names.
    basis : str
        What decided it, in words: ``"specificity (...)"``, ``"overlap (...)"`` or
        ``"severe folding (...)"``.
    """

    better: str
    worse: str
    basis: str

    def to_dict(self) -> dict:
        return {"better": self.better, "worse": self.worse, "basis": self.basis}


@dataclass(frozen=True)
class OpenPair:
    """A pair the verdict leaves open, and why.

    Attributes
    ----------
    a, b : str
        Registration names (`a` has the lower specificity).
    reason : str
        Why the evidence does not decide it, in words.
    leans_to : str or None
        The registration the smoother-fields rule prefers where it may not decide: between
        registrations of different (or unknown) families. A hint, not a claim: the
        known-truth benchmark's record of such leans is in ``docs/verdict.md``. None where
        the evidence leans nowhere, or also the other way.
    """

    a: str
    b: str
    reason: str
    leans_to: str | None = None

    def to_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "reason": self.reason, "leans_to": self.leans_to}


@dataclass(frozen=True)
class Verdict:
    """The headline: which registrations are best, what is decided and what is open.

    Attributes
    ----------
    ranking : tuple of str
        Every registration in the verdict's order: the better of every decided pair
        before the worse (an order that extends the decisions), and where the decisions
        leave a choice the lower specificity first (step by step, of the registrations
        that no remaining one is decided better than, the lowest next). Only the
        decided pairs are claims; the order between registrations the decisions do not
        order is not one. The reports list registrations in this order.
    best : tuple of str
        The registrations no other registration is decided better than, by specificity:
        one name where the evidence decides the best, more where it leaves them open.
    text : tuple of str
        The verdict as sentences.
    decisions : tuple of Decision
        Every ordered pair the verdict asserts (the module docstring gives the rules); a
        pair not listed is open.
    open_pairs : tuple of OpenPair
        Every pair not decided, with the reason.
    """

    ranking: tuple[str, ...]
    best: tuple[str, ...]
    text: tuple[str, ...]
    decisions: tuple[Decision, ...] = ()
    open_pairs: tuple[OpenPair, ...] = ()

    @property
    def decided(self) -> bool:
        """Whether one registration is decided better than every other."""
        return _decided_best(self.best, self.decisions, self.ranking)

    def to_dict(self) -> dict:
        return {
            "ranking": list(self.ranking),
            "best": list(self.best),
            "text": list(self.text),
            "decisions": [d.to_dict() for d in self.decisions],
            "open": [p.to_dict() for p in self.open_pairs],
        }


def _join(names: Sequence[str]) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def _verdict_order(names: Sequence[str], decisions: Sequence[Decision], spec) -> tuple[str, ...]:
    """The verdict's order: a linear order that extends the decided-better partial order.

    Step by step, of the registrations that no remaining one is decided better than, the
    one with the lowest specificity comes next (equal ones in the order of `names`). So
    the better of every decided pair comes first, and a registration comes as early as the
    decisions allow: it follows a worse-scoring one only where a decision puts a
    registration it must follow after that one. (The order level by level of the decision
    graph put a registration last in every measure above one that only waited for a
    decision to clear; issue 44.)

    Parameters
    ----------
    names : sequence of str
    decisions : sequence of Decision
        Acyclic (the verdict withdraws decisions on a cycle).
    spec : mapping of str to float
        Each registration's specificity (the tie-break; NaN last).

    Returns
    -------
    tuple of str
    """

    position = {n: k for k, n in enumerate(names)}

    def key(n: str) -> tuple:
        v = float(spec[n])
        return (math.isnan(v), 0.0 if math.isnan(v) else v, position[n])

    remaining = list(names)
    order: list[str] = []
    while remaining:
        blocked = {d.worse for d in decisions if d.better in remaining}
        # every one blocked: a cycle (the verdict leaves none): the tie-break alone decides
        free = [n for n in remaining if n not in blocked] or remaining
        nxt = min(free, key=key)
        order.append(nxt)
        remaining.remove(nxt)
    return tuple(order)


def verdict(
    scores: Mapping[str, Any],
    comparisons: Sequence[Comparison],
    *,
    has_labels: bool,
) -> Verdict:
    """Decide, pair by pair, which registrations are better, and say so in words.

    The rules are in the module docstring. Without subject-level comparisons (confidence
    not computed) no difference is known to be separable, so only severe folding decides.

    Parameters
    ----------
    scores : dict of str to RegistrationScores
        (:class:`itk_nrreval.evaluation.RegistrationScores`, which holds this verdict: not
        imported here.)
    comparisons : sequence of Comparison
        From :func:`itk_nrreval.measures.confidence.compare` (empty: no confidence computed).
    has_labels : bool
        Whether the overlap is a measure here.

    Returns
    -------
    Verdict
    """
    names = list(scores)
    spec = {n: scores[n].specificity.value for n in names}
    n_samples = min((int(scores[n].specificity.n_samples) for n in names), default=MIN_SAMPLES)
    if n_samples < MIN_SAMPLES:
        return _unconverged(scores, n_samples, has_labels)
    rough = {n: float(scores[n].plausibility.sdlogj) for n in names}
    folded = {n: float(scores[n].plausibility.folded_fraction) for n in names}
    deforms = {n: _deforms_locally(scores[n]) for n in names}
    family = {n: scores[n].family for n in names}
    overlap = {n: scores[n].measures().get(_OVERLAP, math.nan) for n in names}
    sep = {(c.measure, c.a, c.b): c for c in comparisons}

    def comparison(measure: str, a: str, b: str) -> Comparison | None:
        return sep.get((measure, a, b)) or sep.get((measure, b, a))

    def prefers(measure: str, a: str, b: str, *, lower: bool) -> str | None:
        """The registration `measure` separably prefers, or None."""
        c = comparison(measure, a, b)
        if c is None or not c.separable:
            return None
        a_minus_b = c.difference if c.a == a else -c.difference
        return (a if a_minus_b < 0 else b) if lower else (a if a_minus_b > 0 else b)

    decisions: list[Decision] = []
    open_pairs: list[OpenPair] = []
    for a, b in itertools.combinations(names, 2):
        a, b = sorted((a, b), key=spec.get)
        by_spec = prefers(_SPECIFICITY, a, b, lower=True)
        by_overlap = prefers(_OVERLAP, a, b, lower=False) if has_labels else None
        flagged = {n for n in (a, b) if scores[n].flags}
        evidence = _evidence(
            a, b, by_spec, by_overlap, spec, overlap, rough, flagged, folded, deforms
        )
        _add_smoother_evidence(
            evidence, comparison(_SPECIFICITY, a, b), spec, rough, folded, deforms, family
        )
        _add_description_length(evidence, scores[a], scores[b])
        decision = _decide(a, b, evidence, rough, folded)
        if decision is not None:
            decisions.append(decision)
        else:
            reason = _why_open(evidence, rough, has_labels, bool(comparisons))
            open_pairs.append(OpenPair(a, b, reason, _lean(evidence)))
    decisions, contradicted = _without_cycles(decisions)
    for d in contradicted:
        a, b = sorted((d.better, d.worse), key=spec.get)
        reason = f"the evidence contradicts itself: {d.better} > {d.worse} by {d.basis}, yet "
        open_pairs.append(OpenPair(a, b, reason + f"{d.worse} > {d.better} through others"))

    ranking = _verdict_order(names, decisions, spec)
    best = _best(names, decisions, spec)
    text = _sentences(scores, best, decisions, open_pairs, has_labels, bool(comparisons))
    return Verdict(ranking, best, text, tuple(decisions), tuple(open_pairs))


class _Preference(NamedTuple):
    """One measure's separable preference within a pair, and what it is worth."""

    preferred: str
    other: str
    gain: float  # ln of the specificity ratio, or of the overlap odds ratio, in its favour
    discount: str | None  # why not evidence: "rougher", "flagged", "folds", "small",
    # "families" (the smoother-fields rule across families); None: it is
    # the smoother-fields rule (SMOOTHNESS_RATE): the rougher's advantage at the top of its
    # interval, as a ratio; None for a separable preference
    rougher_at_most: float | None = None
    why: str | None = None  # the discount in words, where _discounted cannot say it
    z: float | None = None  # the description length's: jackknife standard errors


def _add_description_length(evidence: dict, sa, sb) -> None:
    """Add the description length's evidence: its preference by at least
    :data:`~itk_nrreval.measures.description_length.MIN_Z` jackknife standard errors between
    two registrations of one known family (``family``: method and engine); ``gain`` is the
    difference in bits per subject."""
    da, db = sa.description_length, sb.description_length
    if da is None or db is None or not _one_family(sa.family, sb.family):
        return
    z = z_of_difference(da, db)  # > 0: a's is the shorter
    if not abs(z) >= MIN_Z:
        return
    (w, dw), (l, dl) = ((sa.name, da), (sb.name, db)) if z > 0 else ((sb.name, db), (sa.name, da))
    evidence[_DESCRIPTION_LENGTH] = _Preference(w, l, dl.bits - dw.bits, None, z=abs(z))


def _one_family(fa: tuple | None, fb: tuple | None) -> bool:
    """Whether two registrations are of one known family (the same ``(method, engine)``)."""
    return fa is not None and fa == fb


def _evidence(a, b, by_spec, by_overlap, spec, overlap, rough, flagged, folded, deforms) -> dict:
    """Each measure's separable preference in the pair ``{measure: _Preference}``. It is
    evidence unless the preferred registration's fields are rougher by ``dr`` and the gain
    is below ``EXCHANGE_RATE * dr`` (roughness alone could buy it; for the overlap
    ``OVERLAP_EXCHANGE_RATE``, or ``OVERLAP_RATE_AGAINST_LINEAR`` against a registration
    that does not deform locally, `deforms`), or it is the overlap's
    preference for a flagged registration (what a cheat games), or a preference over a
    registration that folds (:func:`_against_folds`), or specificity's by a small ratio
    (:data:`MIN_SPECIFICITY_RATIO`)."""
    out = {}
    for measure, preferred in ((_SPECIFICITY, by_spec), (_OVERLAP, by_overlap)):
        if preferred is None:
            continue
        other = b if preferred == a else a
        if measure == _SPECIFICITY:
            gain = _log_ratio(spec[other], spec[preferred])
        else:
            gain = _log_ratio(_odds(overlap[preferred]), _odds(overlap[other]))
        discount, why = None, None
        rate = EXCHANGE_RATE if measure == _SPECIFICITY else OVERLAP_EXCHANGE_RATE
        linear = measure == _OVERLAP and deforms[preferred] and not deforms[other]
        if linear:
            rate = OVERLAP_RATE_AGAINST_LINEAR  # SDlogJ is all of preferred's deformation
        if measure == _OVERLAP and preferred in flagged:
            discount = "flagged"
        elif gain < rate * max(0.0, rough[preferred] - rough[other]):
            discount = "rougher"
        elif why := _against_folds(measure, rate, preferred, other, gain, rough, folded):
            discount = "folds"
        elif measure == _SPECIFICITY and (why := _small(preferred, other, gain, rough)):
            discount = "small"
        elif linear and rough[preferred] > rough[other]:  # evidence: say why it counts
            why = (
                f"{other} does not deform locally, so {preferred}'s SDlogJ is all of its local "
                f"deformation, and {math.exp(gain):.2f}x the odds is more than the "
                f"{math.exp(rate * (rough[preferred] - rough[other])):.2f}x it could buy"
            )
        out[measure] = _Preference(preferred, other, gain, discount, why=why)
    return out


def _against_folds(measure, rate, preferred, other, gain, rough, folded) -> str | None:
    """Why `measure`'s preference for `preferred` is no evidence against `other`, which
    folds, in words; None where it is (the gain reaches what ``preferred``'s own roughness
    could buy at the measure's exchange `rate`, or `other` folds less than
    :data:`NO_FOLDING_FRACTION`, or no more than `preferred`)."""
    if folded[other] < NO_FOLDING_FRACTION or folded[other] <= folded[preferred]:
        return None
    if gain >= rate * rough[preferred]:
        return None
    what = "lower specificity" if measure == _SPECIFICITY else "the odds of overlap"
    return (
        f"{other} folds {folded[other]:.1%} of its voxels, so SDlogJ ({rough[other]:.2f} vs "
        f"{rough[preferred]:.2f}) does not say which fields are the rougher; "
        f"{preferred}'s {math.exp(gain):.2f}x {what} is less than the "
        f"{math.exp(rate * rough[preferred]):.2f}x its own roughness could buy"
    )


def _small(preferred, other, gain, rough) -> str | None:
    """Why specificity's preference for `preferred` is too small to be evidence, in words;
    None where it is not (its ratio reaches :data:`MIN_SPECIFICITY_RATIO`, or its fields are
    smoother by at least :data:`MIN_ROUGHNESS_DIFFERENCE`)."""
    if gain >= math.log(MIN_SPECIFICITY_RATIO):
        return None
    if rough[other] - rough[preferred] >= MIN_ROUGHNESS_DIFFERENCE:
        return None
    return (
        f"{preferred}'s specificity is only {math.exp(gain):.2f}x lower, below the "
        f"{MIN_SPECIFICITY_RATIO:g}x a difference must reach where its fields are not clearly "
        f"smoother (SDlogJ {rough[preferred]:.2f} vs {rough[other]:.2f})"
    )


def _add_smoother_evidence(
    evidence: dict, c: Comparison | None, spec, rough, folded, deforms, family
) -> None:
    """Add specificity's evidence for the smoother registration of a pair when the rougher
    one's specificity advantage, at the top of its interval, is below what
    :data:`SMOOTHNESS_RATE` says its extra roughness must buy (``gain`` is then minus that
    top). Separable evidence already found, or a discount other than roughness, stays.

    Only between two registrations of one known family (`family`: name -> ``(method,
    engine)`` or None): across families the same preference is recorded as no evidence
    (discount ``"families"``), so an open pair's reason says which way it leans."""
    if c is None:
        return
    s, r = sorted((c.a, c.b), key=rough.get)
    dr = rough[r] - rough[s]
    found = evidence.get(_SPECIFICITY)
    if dr < MIN_ROUGHNESS_DIFFERENCE or (found is not None and found.discount != "rougher"):
        return
    if not deforms[s]:
        return  # no local deformation (affine): SDlogJ cannot see what it leaves out
    if folded[s] > folded[r]:
        return  # folds: roughness that SDlogJ (over the voxels that do not fold) ranks poorly
    if folded[s] >= NO_FOLDING_FRACTION:
        return  # one that folds is not credited for its smoothness, whatever its SDlogJ
    lowest_r_minus_s = c.ci95[0] if c.a == r else -c.ci95[1]
    top_gain = _log_ratio(spec[s], spec[s] + lowest_r_minus_s)  # r's best case
    if not top_gain < SMOOTHNESS_RATE * dr:
        return
    lean = _Preference(s, r, -top_gain, None, math.exp(top_gain))
    if not _one_family(family[s], family[r]):
        # Roughness is no common currency across families: in the benchmark's FRESH11, SyN
        # (SDlogJ 0.20) was preferred this way over demons at 3 mm (0.30), which corresponded
        # better. The rate was set on settings of one engine.
        why = f"{_too_little(lean, rough)}, so it leans to {s}; {_across(s, r, family)}"
        lean = lean._replace(discount="families", why=why)
    evidence[_SPECIFICITY] = lean


def _across(s: str, r: str, family) -> str:
    """Why the smoother-fields rule does not decide between `s` and `r`, in words."""
    if family[s] is None or family[r] is None:
        unknown = " and ".join(n for n in (s, r) if family[n] is None)
        return (
            f"not decided, because the family of {unknown} is unknown (the manifest's "
            "parameters give no method and engine), and roughness is compared only within one"
        )
    fs, fr = ("/".join(family[n]) for n in (s, r))
    return (
        f"not decided, because {s} ({fs}) and {r} ({fr}) are of different families, "
        "whose roughness is no common currency"
    )


def _deforms_locally(score) -> bool:
    """Whether a registration deforms locally: its subjects' median non-linear displacement
    (RMS, mm) is at least :data:`~itk_nrreval.measures.subject_qc.IDENTITY_MM` (an affine
    registration's is 0 to round-off). Without per-subject measures: its SDlogJ is at least
    :data:`MIN_ROUGHNESS_DIFFERENCE`."""
    from .subject_qc import IDENTITY_MM

    values = [
        q.deformation.get("nonlinear_rms_mm")
        for q in (score.subjects or ())
        if not q.reference and q.deformation
    ]
    values = [v for v in values if v is not None and math.isfinite(v)]
    if not values:
        return float(score.plausibility.sdlogj) >= MIN_ROUGHNESS_DIFFERENCE
    return statistics.median(values) >= IDENTITY_MM


def _lean(evidence: dict) -> str | None:
    """The registration the smoother-fields rule prefers across families (discount
    ``"families"``), unless evidence that counts prefers the other."""
    p = evidence.get(_SPECIFICITY)
    if p is None or p.discount != "families" or p.other in _counted(evidence):
        return None
    return p.preferred


def _counted(evidence: dict) -> set[str]:
    """The registrations the evidence (not discounted) prefers: none, one, or both."""
    return {p.preferred for p in evidence.values() if p.discount is None}


def _decide(a, b, evidence, rough, folded) -> Decision | None:
    for w, l in ((a, b), (b, a)):
        if folded[l] >= SEVERE_FOLDED_FRACTION and folded[w] < NO_FOLDING_FRACTION:
            return Decision(w, l, f"severe folding ({l} folds {folded[l]:.0%} of its voxels)")
    if len(_counted(evidence)) != 1:
        return None  # no evidence, or the measures' evidence disagrees
    (w,) = _counted(evidence)
    l = b if w == a else a
    used = [m for m, p in evidence.items() if p.discount is None]
    gains = [
        f"{math.exp(evidence[m].gain):.2f}x "
        + ("the odds of overlap" if m == _OVERLAP else f"lower {_WORD[m]}")
        for m in used
        if evidence[m].rougher_at_most is None and evidence[m].z is None
    ]
    gains += [
        f"{evidence[m].gain:.0f} bits per subject shorter, {evidence[m].z:.1f} standard errors"
        for m in used
        if evidence[m].z is not None
    ]
    details = [f"separable: {', '.join(gains)}"] if gains else []
    details += [
        _too_little(p, rough) for p in evidence.values() if p.rougher_at_most and p.discount is None
    ]
    details += [p.why for p in evidence.values() if p.discount is None and p.why]
    details.append(_roughness(w, l, rough))
    details += [_discounted(m, p, rough) for m, p in evidence.items() if p.discount]
    return Decision(w, l, f"{' and '.join(_WORD[m] for m in used)} ({'; '.join(details)})")


def _too_little(p: _Preference, rough) -> str:
    """Why the smoother registration is preferred by the smoother-fields rule, in words."""
    dr = rough[p.other] - rough[p.preferred]
    return (
        f"{p.other}'s fields are {dr:.2f} rougher in SDlogJ, and its specificity advantage is "
        f"at most {p.rougher_at_most:.2f}x, less than the {math.exp(SMOOTHNESS_RATE * dr):.2f}x "
        "that much roughness must buy"
    )


def _discounted(measure: str, p: _Preference, rough) -> str:
    """Why a measure's preference is not evidence, in words."""
    if p.why is not None:
        return p.why
    if p.discount == "flagged":
        return f"only the overlap prefers {p.preferred}, which is flagged (a cheat games overlap)"
    what = "lower specificity" if measure == _SPECIFICITY else "higher overlap"
    return (
        f"{p.preferred}'s {what} comes with fields "
        f"{_times(rough[p.preferred], rough[p.other])}rougher (SDlogJ "
        f"{rough[p.preferred]:.2f} vs {rough[p.other]:.2f}), and its advantage is not larger "
        "than what roughness alone can buy"
    )


def _basis_words(basis: str) -> list[str]:
    """The kinds of evidence a decision's basis names: "specificity", "overlap", ..."""
    return basis.split(" (")[0].split(" and ")


def _odds(p: float) -> float:
    return p / (1.0 - p) if p < 1.0 else math.inf


def _log_ratio(x: float, y: float) -> float:
    """ln(x / y) for positive x, y; at the edges -inf (x <= 0) or inf (y <= 0), not an
    error."""
    if not x > 0:
        return -math.inf
    if not y > 0 or math.isinf(x):
        return math.inf
    return math.log(x / y)


def _roughness(w: str, l: str, rough) -> str:
    word = "no rougher" if rough[w] <= rough[l] else "rougher"
    return f"fields {word}: SDlogJ {rough[w]:.2f} vs {rough[l]:.2f}"


def _times(x: float, y: float) -> str:
    # a factor over a near-zero SDlogJ (an affine registration's) means nothing
    return f"{x / y:.1f}x " if y >= 0.01 else ""


def _why_open(evidence, rough, has_labels, confidence) -> str:
    if not confidence:
        return "subject-level confidence was not computed, so no difference is known to hold"
    if len(_counted(evidence)) == 2:  # each measure that counts, and whom it prefers
        return ", ".join(
            f"{_WORD[m]} prefers {p.preferred}" for m, p in evidence.items() if p.discount is None
        )
    if evidence:
        return "; ".join(_discounted(m, p, rough) for m, p in evidence.items())
    if has_labels:
        return "neither specificity nor overlap differs separably"
    return "the specificity difference is not separable"


def _without_cycles(decisions: list[Decision]) -> tuple[list[Decision], list[Decision]]:
    """The decisions that lie on no cycle, and those that do.

    Decisions by different evidence can go round (a > b by folding, b > c and c > a by
    specificity): then at least one of them is wrong, and the data do not say which, so
    every decision between registrations that reach each other is withdrawn.
    """
    reach = {d.better: set() for d in decisions} | {d.worse: set() for d in decisions}
    for d in decisions:
        reach[d.better].add(d.worse)
    changed = True
    while changed:  # transitive closure: a handful of registrations
        changed = False
        for node, below in reach.items():
            grown = below.union(*(reach[m] for m in below))
            if grown != below:
                reach[node], changed = grown, True
    kept = [d for d in decisions if d.better not in reach[d.worse]]
    return kept, [d for d in decisions if d.better in reach[d.worse]]


def _decided_best(best, decisions, names) -> bool:
    """Whether the one best registration is decided better than every other."""
    if len(best) != 1:
        return False
    beaten = {d.worse for d in decisions if d.better == best[0]}
    return beaten == set(names) - {best[0]}


def _best(names, decisions, spec) -> tuple[str, ...]:
    """The registrations no other is decided better than, by specificity (lower first)."""
    beaten = {d.worse for d in decisions}
    return tuple(n for n in _verdict_order(names, (), spec) if n not in beaten)


def _too_few_samples(n_samples: int) -> str:
    return (
        f"M = {n_samples:,} samples is below the minimum of {MIN_SAMPLES:,} for a verdict: "
        "the scores have not converged"
    )


def _unconverged(scores, n_samples: int, has_labels: bool) -> Verdict:
    """The verdict with too few specificity samples: every pair open, and why."""
    names = list(scores)
    spec = {n: scores[n].specificity.value for n in names}
    reason = _too_few_samples(n_samples)
    open_pairs = [
        OpenPair(*sorted((a, b), key=spec.get), reason) for a, b in itertools.combinations(names, 2)
    ]
    ranking = _verdict_order(names, (), spec)
    if len(names) == 1:
        return Verdict(ranking, ranking, (f"{names[0]} is the only registration.",), (), ())
    text = [
        f"Not decided: {reason} (rerun with at least {MIN_SAMPLES:,} specificity samples, "
        "--samples or n_samples, for a verdict; the scores below are for a quick look).",
        f"0 of {len(open_pairs)} pairs decided, {len(open_pairs)} open.",
        *_closing(scores, names, has_labels),
    ]
    return Verdict(ranking, ranking, tuple(text), (), tuple(open_pairs))


def _closing(scores, names, has_labels) -> list[str]:
    """The verdict's last sentences: the highest overlap, and each flagged registration."""
    text = []
    if has_labels and all(_OVERLAP in scores[n].measures() for n in names):
        value = {n: scores[n].measures()[_OVERLAP] for n in names}
        top_o = max(names, key=lambda n: value[n])
        text.append(f"Highest inverse-volume overlap (the ground-truth reference): {top_o}.")
    for n in names:
        if scores[n].flags:
            text.append(
                f"{n} is flagged: {'; '.join(scores[n].flags)}. A flag is a warning, not a "
                "decision: only severe folding decides against it."
            )
    return text


def _by_what(top: str, decisions) -> str:
    """The measures by which `top` was decided better than each other registration, in
    words: those every one of its decisions shares, or, when none is shared, each measure
    with the registrations it decided (never a measure that decided only some of them as
    if it decided all; issue 44)."""
    mine = [d for d in decisions if d.better == top]
    words = {d.worse: _basis_words(d.basis) for d in mine}
    shared = sorted(set.intersection(*(set(w) for w in words.values())))
    if shared:
        return f"by {_join(shared)}"
    by_basis: dict[str, list[str]] = {}
    for d in mine:
        by_basis.setdefault(" and ".join(_basis_words(d.basis)), []).append(d.worse)
    return "; ".join(f"by {basis} over {_join(worse)}" for basis, worse in by_basis.items())


def _sentences(scores, best, decisions, open_pairs, has_labels, confidence) -> tuple[str, ...]:
    text = []
    names = list(scores)
    if len(names) == 1:
        return (f"{names[0]} is the only registration.",)
    top = best[0]
    if _decided_best(best, decisions, names):
        text.append(
            f"{top} is best: decided better than every other registration "
            f"({_by_what(top, decisions)})."
        )
    elif len(best) == 1:
        text.append(
            f"{top} is best: no registration is decided better than it, and every other is "
            "decided worse than at least one registration."
        )
    else:
        text.append(
            f"Not decided between {_join(best)}: no registration is decided better than "
            f"these, and the evidence does not order them ({top} has the lowest specificity)."
        )
        among = [p for p in open_pairs if p.a in best and p.b in best]
        for p in among[:4]:
            text.append(f"{p.a} and {p.b}: not decided: {p.reason}.")
        if len(among) > 4:
            text.append(f"({len(among) - 4} more open pairs among them: results.json 'open'.)")
    if not confidence:
        text.append(
            "Subject-level confidence was not computed: no difference is known to hold on "
            "other subjects, so only severe folding decides."
        )
    n_pairs = len(decisions) + len(open_pairs)
    leaning = [p for p in open_pairs if p.leans_to is not None]
    lean = (
        f" ({len(leaning)} of them {'leans' if len(leaning) == 1 else 'lean'} one way by "
        "smoother fields across families, a hint and not a decision: results.json 'open', "
        "'leans_to')"
        if leaning
        else ""
    )
    text.append(f"{len(decisions)} of {n_pairs} pairs decided, {len(open_pairs)} open{lean}.")
    if leaning:
        text.append(_leaning_sentence(leaning))
    return tuple(text + _closing(scores, names, has_labels))


#: The most leaning pairs the verdict's text names (the rest: results.json 'open').
_LEANS_NAMED = 6


def _leaning_sentence(leaning: Sequence[OpenPair]) -> str:
    """The open pairs that lean, named (the registration leaned to first), so a reader
    without labels sees the hints without opening results.json."""
    named = [f"{p.leans_to} over {p.b if p.leans_to == p.a else p.a}" for p in leaning]
    more = len(named) - _LEANS_NAMED
    shown = "; ".join(named[:_LEANS_NAMED]) + (f"; and {more} more" if more > 0 else "")
    return f"Leaning, not decided: {shown}."
