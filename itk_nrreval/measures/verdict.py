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
  lower specificity for 0.1 rougher fields, 4x for 0.25; between two registrations that
  deform locally and are not of one known family, :data:`EXCHANGE_RATE_ACROSS_FAMILIES`: a
  unit of SDlogJ is not the same roughness across families), and on the log-odds of the
  inverse-volume generalized overlap with :data:`OVERLAP_EXCHANGE_RATE`; where ``b`` does
  not deform locally (an affine registration) the overlap at
  :data:`OVERLAP_RATE_AGAINST_LINEAR`: there SDlogJ is all of ``a``'s local deformation,
  the correspondence it gains included (specificity's preference there, in 2D where ``a``
  folds less than :data:`NO_FOLDING_FRACTION`, is evidence from
  :data:`SPECIFICITY_DECIDES_AGAINST_LINEAR` x SDlogJ, and from
  :data:`SPECIFICITY_RATE_AGAINST_LINEAR` x SDlogJ a lean, ``OpenPair.leans_to``); smoother
  fields are not charged; or
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
  were separably better). Against a ``b`` that clearly folds (at least
  :data:`CLEARLY_FOLDS_FRACTION`) the rates are lower, :data:`SPECIFICITY_RATE_AGAINST_FOLDS`
  and :data:`OVERLAP_RATE_AGAINST_FOLDS`: there the truth sided with 209 of the benchmark's
  211 such specificity preferences. For the overlap only outside
  :data:`OVERLAP_AGAINST_FOLDS_DIMENSIONS` (in 2D the overlap's preference there agreed
  with the truth on every tuning case); or
- it is specificity's preference for an ``a`` that clearly folds (at least
  :data:`CLEARLY_FOLDS_FRACTION`) and more than ``b``, however large: SDlogJ, over the
  voxels that do not fold, does not measure what ``a``'s folds buy (the benchmark's
  ``FRESH23``: a 10 mm B-spline folding 10.9%, SDlogJ 0.99, was decided better by a 1.24x
  lower specificity than demons at 0.1 mm field smoothing folding 3.4%, SDlogJ 2.43, that
  corresponded better); or
- it is specificity's preference by less than :data:`MIN_SPECIFICITY_RATIO` (1.2x) for a
  registration whose fields are not smoother by at least :data:`MIN_ROUGHNESS_DIFFERENCE`.

The charge has a converse, for specificity only (:data:`SMOOTHNESS_RATE`): when ``a``'s
fields are rougher by ``dr`` (at least :data:`MIN_ROUGHNESS_DIFFERENCE`) and its
specificity advantage, even at the top of its subject-level interval, is below
``exp(SMOOTHNESS_RATE * dr)``, that is specificity's evidence for the smoother ``b``, if
``b`` deforms locally (its subjects' median non-linear displacement is at least
:data:`~itk_nrreval.measures.subject_qc.IDENTITY_MM`; an affine registration's zero SDlogJ says
nothing of the deformation it leaves out, so against affine, in 2D, only at
:data:`SMOOTHNESS_RATE_AGAINST_LINEAR` x SDlogJ and where ``a`` folds less than
:data:`NO_FOLDING_FRACTION`), folds no more than ``a`` and less than
:data:`NO_FOLDING_FRACTION` (folds are roughness that SDlogJ, taken over the voxels that
do not fold, ranks poorly: 3D B-splines folding 3-6% had a lower SDlogJ than demons that
corresponded better; in ``FRESH6`` a 25 mm B-spline folding 4.4% was preferred over a
10 mm one folding 8.6% that corresponded better): the
extra roughness bought too little to be correspondence (the flat end of the trade-off's
L-curve: demons or B-splines past their knee, fitting noise). Between the two rates the
pair is the knee, and stays open unless the overlap decides it. Between registrations of
different families (``family``: the same ``method`` and ``engine`` in the manifest's
``parameters`` make one; or where a family is unknown) this converse counts only where the
SDlogJ difference reaches :data:`ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE` and ``a`` folds less
than :data:`NO_FOLDING_FRACTION`: how rough a registration's fields are for the
correspondence they reach is partly a property of its method, so otherwise the open pair's
reason says which way it leans, and nothing is decided.

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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ._pair_evidence import (
    OVERLAP,
    SPECIFICITY,
    RegistrationFacts,
    add_description_length,
    add_smoother_evidence,
    decision,
    deforms_locally,
    lean,
    measure_evidence,
    why_open,
)
from ._verdict_thresholds import (  # the rules' numbers, and how each was set
    ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE,
    CLEARLY_FOLDS_FRACTION,
    EXCHANGE_RATE,
    EXCHANGE_RATE_ACROSS_FAMILIES,
    LINEAR_DIMENSIONS,
    MIN_ROUGHNESS_DIFFERENCE,
    MIN_SAMPLES,
    MIN_SPECIFICITY_RATIO,
    NO_FOLDING_FRACTION,
    OVERLAP_AGAINST_FOLDS_DIMENSIONS,
    OVERLAP_EXCHANGE_RATE,
    OVERLAP_RATE_AGAINST_FOLDS,
    OVERLAP_RATE_AGAINST_LINEAR,
    SEVERE_FOLDED_FRACTION,
    SMOOTHNESS_RATE,
    SMOOTHNESS_RATE_AGAINST_LINEAR,
    SPECIFICITY_DECIDES_AGAINST_LINEAR,
    SPECIFICITY_RATE_AGAINST_FOLDS,
    SPECIFICITY_RATE_AGAINST_LINEAR,
)
from .confidence import Comparison

__all__ = [
    "Decision",
    "OpenPair",
    "Verdict",
    "verdict",
    "EXCHANGE_RATE",
    "EXCHANGE_RATE_ACROSS_FAMILIES",
    "SMOOTHNESS_RATE",
    "SMOOTHNESS_RATE_AGAINST_LINEAR",
    "OVERLAP_EXCHANGE_RATE",
    "OVERLAP_RATE_AGAINST_LINEAR",
    "SPECIFICITY_RATE_AGAINST_LINEAR",
    "SPECIFICITY_DECIDES_AGAINST_LINEAR",
    "ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE",
    "LINEAR_DIMENSIONS",
    "OVERLAP_AGAINST_FOLDS_DIMENSIONS",
    "SPECIFICITY_RATE_AGAINST_FOLDS",
    "OVERLAP_RATE_AGAINST_FOLDS",
    "CLEARLY_FOLDS_FRACTION",
    "MIN_ROUGHNESS_DIFFERENCE",
    "MIN_SPECIFICITY_RATIO",
    "SEVERE_FOLDED_FRACTION",
    "NO_FOLDING_FRACTION",
    "MIN_SAMPLES",
]


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
        The registration specificity leans to where it may not decide: by the smoother-fields
        rule between registrations of different (or unknown) families whose SDlogJ differ by
        less than :data:`ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE` (or whose rougher one folds),
        or, in 2D, by a lower
        specificity than an affine registration's beyond
        :data:`SPECIFICITY_RATE_AGAINST_LINEAR` x SDlogJ (short of
        :data:`SPECIFICITY_DECIDES_AGAINST_LINEAR` x SDlogJ). A hint, not a claim: the
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
    dimension: int | None = None,
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
    dimension : int, optional
        The images' dimension (2 or 3). A rule set on cases of one dimension alone is used
        only there (:data:`SPECIFICITY_RATE_AGAINST_LINEAR`,
        :data:`SPECIFICITY_DECIDES_AGAINST_LINEAR`, :data:`SMOOTHNESS_RATE_AGAINST_LINEAR` and
        :data:`OVERLAP_AGAINST_FOLDS_DIMENSIONS`: 2D); None (unknown): nowhere.

    Returns
    -------
    Verdict
    """
    names = list(scores)
    spec = {n: scores[n].specificity.value for n in names}
    n_samples = min((int(scores[n].specificity.n_samples) for n in names), default=MIN_SAMPLES)
    if n_samples < MIN_SAMPLES:
        return _unconverged(scores, n_samples, has_labels)
    facts = RegistrationFacts(
        spec=spec,
        overlap={n: scores[n].measures().get(OVERLAP, math.nan) for n in names},
        rough={n: float(scores[n].plausibility.sdlogj) for n in names},
        folded={n: float(scores[n].plausibility.folded_fraction) for n in names},
        deforms={n: deforms_locally(scores[n]) for n in names},
        family={n: scores[n].family for n in names},
        dimension=dimension,
    )
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
        by_spec = prefers(SPECIFICITY, a, b, lower=True)
        by_overlap = prefers(OVERLAP, a, b, lower=False) if has_labels else None
        flagged = {n for n in (a, b) if scores[n].flags}
        found = measure_evidence(a, b, by_spec, by_overlap, facts, flagged=flagged)
        add_smoother_evidence(found, comparison(SPECIFICITY, a, b), facts)
        add_description_length(found, scores[a], scores[b])
        decided = decision(a, b, found, facts)
        if decided is not None:
            decisions.append(Decision(*decided))
        else:
            reason = why_open(found, facts.rough, has_labels, bool(comparisons))
            open_pairs.append(OpenPair(a, b, reason, lean(found)))
    decisions, contradicted = _without_cycles(decisions)
    for d in contradicted:
        a, b = sorted((d.better, d.worse), key=spec.get)
        reason = f"the evidence contradicts itself: {d.better} > {d.worse} by {d.basis}, yet "
        open_pairs.append(OpenPair(a, b, reason + f"{d.worse} > {d.better} through others"))

    ranking = _verdict_order(names, decisions, spec)
    best = _best(names, decisions, spec)
    text = _sentences(scores, best, decisions, open_pairs, has_labels, bool(comparisons))
    return Verdict(ranking, best, text, tuple(decisions), tuple(open_pairs))


def _basis_words(basis: str) -> list[str]:
    """The kinds of evidence a decision's basis names: "specificity", "overlap", ..."""
    return basis.split(" (")[0].split(" and ")


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
    if has_labels and all(OVERLAP in scores[n].measures() for n in names):
        value = {n: scores[n].measures()[OVERLAP] for n in names}
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
        "smoother fields across families or by specificity against affine, a hint and not a "
        "decision: results.json 'open', 'leans_to')"
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
