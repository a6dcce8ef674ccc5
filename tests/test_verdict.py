"""The verdict: a class-matching cheat is flagged and ranked last; intervals, sentences and
the ordered pairs it decides."""

from __future__ import annotations

import dataclasses
import itertools
import json

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from test_evaluate import N_IMAGES, make_case

import itk_nrreval as nr
from data_synth.cheat import class_matching_cheat
from itk_nrreval.cli import main
from itk_nrreval.evaluation import verdict
from itk_nrreval.measures.confidence import compare
from itk_nrreval.measures.verdict import LINEAR_DIMENSIONS

KW = dict(n_samples=3000, seed=2, progress=False)


@pytest.fixture(scope="module")
def cheat_case(tmp_path_factory):
    """make_case's truth / perturbed / identity registrations plus Rohlfing's cheat."""
    tmp_path = tmp_path_factory.mktemp("cheat")
    data = make_case(tmp_path)
    # reference classes: the template's labels (0 background, 1..3): its intensity / 100
    template = sitk.ReadImage(str(tmp_path / "template.nii.gz"))
    classes = sitk.GetImageFromArray(
        np.round(sitk.GetArrayFromImage(template) / 100.0).astype(np.int16)
    )
    classes.CopyInformation(template)
    items = []
    for i in range(N_IMAGES):
        subject = sitk.ReadImage(str(tmp_path / f"lab{i}.nii.gz"))  # on the template grid
        cheat = class_matching_cheat(classes, subject, sitk.AffineTransform(2))
        path = tmp_path / f"cheat{i}.h5"
        sitk.WriteTransform(cheat, str(path))
        items.append(path.name)
    data["registrations"]["cheat"] = {"reference": "template.nii.gz", "transforms": items}
    manifest = tmp_path / "manifest.yaml"
    manifest.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.warns(RuntimeWarning, match="'cheat' is flagged as implausible"):
        result = nr.evaluate(manifest, **KW)
    return manifest, result


def test_cheat_is_flagged_and_never_decided_better_than_the_truth(cheat_case):
    """The cheat folds and matches labels: flagged; the truth is decided better than it and
    than every other registration; the cheat's overlap decides nothing in its favour."""
    _, result = cheat_case
    cheat = result.scores["cheat"]
    assert cheat.flags and "fold" in cheat.flags[0]
    assert cheat.plausibility.folded_fraction > 1e-3
    assert cheat.plausibility.jacobian_min <= 0  # never clipped
    v = result.verdict
    assert v.best == ("truth",) and v.decided
    assert v.ranking[0] == "truth"
    assert not any(d.better == "cheat" for d in v.decisions)
    assert not result.scores["truth"].flags and not result.scores["perturbed"].flags
    assert any(t.startswith("cheat is flagged: ") for t in v.text)
    assert v.text[0].startswith("truth is best: decided better than every other registration")


def test_intervals_comparisons_and_results_json(cheat_case, tmp_path):
    manifest, result = cheat_case
    truth = result.scores["truth"]
    iv = truth.intervals["specificity"]
    assert iv.lo < truth.specificity.value < iv.hi
    # subject-level uncertainty is far larger than Monte-Carlo error
    assert iv.stderr > 3 * truth.specificity.stderr
    pair = next(
        c
        for c in result.comparisons
        if c.measure == "specificity" and {c.a, c.b} == {"truth", "identity"}
    )
    assert pair.separable and (pair.difference < 0) == (pair.a == "truth")
    assert sum(s.probability_best["specificity"] for s in result.scores.values()) == (
        pytest.approx(1.0)
    )
    out = tmp_path / "out"
    assert main(["evaluate", str(manifest), "--out", str(out), "--samples", "3000"]) == 0
    res = json.loads((out / "results.json").read_text())
    reg = res["registrations"]["cheat"]
    lo, hi = reg["specificity"]["ci95"]
    assert lo < reg["specificity"]["value"] < hi
    p = reg["plausibility"]
    assert set(p) >= {
        "folded_fraction",
        "sdlogj",
        "jacobian_min",
        "jacobian_max",
        "inverse_consistency_mm",
        "flags",
    }
    assert p["flags"] and res["registrations"]["truth"]["plausibility"]["flags"] == []
    c = res["comparisons"][0]
    assert set(c) == {"measure", "a", "b", "difference", "ci95", "separable"}
    assert res["verdict"]["best"] == ["truth"] and res["verdict"]["text"]
    decided = {(d["better"], d["worse"]): d["basis"] for d in res["verdict"]["decisions"]}
    for name in ("perturbed", "identity", "cheat"):
        assert decided[("truth", name)].startswith("specificity")
    opened = {frozenset((p["a"], p["b"])): p["reason"] for p in res["verdict"]["open"]}
    assert len(decided) + len(opened) == 6  # every pair: decided or open, with a reason
    assert not set(map(frozenset, decided)) & set(opened)
    assert all(reason for reason in opened.values())
    summary = (out / "summary.md").read_text()
    assert summary.startswith(res["verdict"]["text"][0])
    assert "95% CI" in summary and "cheat is flagged" in summary
    json.dumps(res, allow_nan=False)  # valid JSON: no NaN anywhere


def test_confidence_off_gives_no_intervals(tmp_path):
    make_case(tmp_path)
    result = nr.evaluate(tmp_path / "manifest.yaml", confidence=False, **KW)
    assert result.comparisons == () and result.scores["truth"].intervals == {}
    assert result.verdict.best[0] == "truth"  # lowest specificity, first of the open set
    assert "not computed" in " ".join(result.verdict.text)
    assert result.verdict.decisions == ()  # nothing separable, no severe folding: all open
    assert not result.verdict.decided
    with pytest.raises(ValueError, match="samples: expected an integer >= 2"):
        nr.evaluate(tmp_path / "manifest.yaml", confidence=nr.Confidence(samples=1), **KW)


def test_cli_thresholds_decide_the_flags(cheat_case, tmp_path, capsys):
    manifest, _ = cheat_case
    out = tmp_path / "out"
    args = ["evaluate", str(manifest), "--out", str(out), "--samples", "2000", "--no-figures"]
    loose = ["--flag-folded-mean", "1", "--flag-folded-max", "1", "--flag-sdlogj-ratio", "1e9"]
    assert main(args + loose + ["--no-confidence", "--no-inverse-consistency"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["registrations"]["cheat"]["plausibility"]["flags"] == []
    assert res["registrations"]["cheat"]["plausibility"]["inverse_consistency_mm"] is None
    assert res["options"]["thresholds"]["folded_mean"] == 1.0
    capsys.readouterr()
    assert main(args + ["--flag-folded-mean", "2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--flag-folded-mean: expected a fraction in [0, 1], got '2'" in err


def _deforms_locally(score) -> bool:
    """Whether a registration's subjects' median non-linear displacement reaches 0.01 mm."""
    nonlinear = [
        q.deformation["nonlinear_rms_mm"]
        for q in score.subjects
        if not q.reference and q.deformation.get("nonlinear_rms_mm") is not None
    ]
    return bool(np.median(nonlinear) >= 0.01)


def _rules_allow(w, l, scores, comparisons, has_labels, dimension) -> list[str]:
    """The rules of the verdict (module docstring of itk_nrreval.measures.verdict), restated:
    which of them let `w` be decided better than `l` in images of `dimension` (2, 3 or None:
    unknown)."""
    from itk_nrreval.measures.verdict import (
        ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE,
        CLEARLY_FOLDS_FRACTION,
        EXCHANGE_RATE,
        EXCHANGE_RATE_ACROSS_FAMILIES,
        MIN_ROUGHNESS_DIFFERENCE,
        MIN_SPECIFICITY_RATIO,
        NO_FOLDING_FRACTION,
        OVERLAP_EXCHANGE_RATE,
        OVERLAP_RATE_AGAINST_FOLDS,
        OVERLAP_RATE_AGAINST_LINEAR,
        SEVERE_FOLDED_FRACTION,
        SMOOTHNESS_RATE,
        SMOOTHNESS_RATE_AGAINST_LINEAR,
        SPECIFICITY_DECIDES_AGAINST_LINEAR,
        SPECIFICITY_RATE_AGAINST_FOLDS,
    )

    def deforms_locally(r) -> bool:
        return _deforms_locally(scores[r])

    def winner(measure, lower):
        """The registration of the two that `measure` separably prefers, or None."""
        for c in comparisons:
            if c.measure == measure and {c.a, c.b} == {w, l} and c.separable:
                w_minus_l = c.difference if c.a == w else -c.difference
                return w if bool(w_minus_l < 0) == lower else l
        return None

    by_spec = winner("specificity", lower=True)
    by_overlap = winner("overlap.inverse_volume", lower=False) if has_labels else None

    def too_little(r, o):
        """Whether `r` is smoother than `o` by at least MIN_ROUGHNESS_DIFFERENCE and o's
        specificity advantage, at the bottom of the interval of spec(o) - spec(r), is below
        exp(SMOOTHNESS_RATE * dr), both of one known family, or smoother by at least
        ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE than an `o` that folds less than
        NO_FOLDING_FRACTION; or, in 2D, `r` does not deform locally (affine), `o` does and
        folds less than NO_FOLDING_FRACTION, and the advantage is below
        exp(SMOOTHNESS_RATE_AGAINST_LINEAR * dr)."""
        dr = scores[o].plausibility.sdlogj - scores[r].plausibility.sdlogj
        o_folds = scores[o].plausibility.folded_fraction >= NO_FOLDING_FRACTION
        if not deforms_locally(r):  # affine: no non-linear displacement
            if dimension != 2 or not deforms_locally(o) or o_folds:
                return False  # its own rate, in 2D, against fields that deform and do not fold
            rate = SMOOTHNESS_RATE_AGAINST_LINEAR
        else:
            one_family = scores[r].family is not None and scores[r].family == scores[o].family
            if not one_family and (dr < ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE or o_folds):
                return False  # across families only a large difference, of unfolded fields
            if scores[r].plausibility.folded_fraction > scores[o].plausibility.folded_fraction:
                return False  # r folds more: not the smoother, whatever its SDlogJ
            if scores[r].plausibility.folded_fraction >= NO_FOLDING_FRACTION:
                return False  # r folds: not credited for smoothness at all
            rate = SMOOTHNESS_RATE
        for c in comparisons:
            if (
                c.measure == "specificity"
                and {c.a, c.b} == {r, o}
                and dr >= MIN_ROUGHNESS_DIFFERENCE
            ):
                o_minus_r = c.ci95[0] if c.a == o else -c.ci95[1]
                best_o = scores[r].specificity.value + o_minus_r
                return best_o > 0 and scores[r].specificity.value / best_o < np.exp(rate * dr)
        return False

    def evidence(measure, r):
        """Whether `measure` separably prefers `r` by more than r's rougher fields buy (and,
        for the overlap, r is not flagged)."""
        o = l if r == w else w
        rougher = max(0.0, scores[r].plausibility.sdlogj - scores[o].plausibility.sdlogj)
        if measure == "specificity":
            gain = np.log(scores[o].specificity.value / scores[r].specificity.value)
            fr, fo = scores[r].plausibility.folded_fraction, scores[o].plausibility.folded_fraction
            sr, so = scores[r].plausibility.sdlogj, scores[o].plausibility.sdlogj
            rate = EXCHANGE_RATE  # against affine too: there it may lean, never decide
            one_family = scores[r].family is not None and scores[r].family == scores[o].family
            # across families (or unknown ones), against one that deforms locally, a higher rate
            charge = rate if one_family or not deforms_locally(o) else EXCHANGE_RATE_ACROSS_FAMILIES
            if by_spec == r and gain >= charge * rougher:
                # r clearly folds (2.5%), and more than o: no evidence, whatever its SDlogJ
                if fr >= CLEARLY_FOLDS_FRACTION and fr > fo:
                    return False
                # against one that folds more (>= 1%): r charged by its own SDlogJ, as if
                # o's fields were flat; against one folding 2.5% or more at a lower rate
                own = SPECIFICITY_RATE_AGAINST_FOLDS if fo >= CLEARLY_FOLDS_FRACTION else rate
                if fo >= NO_FOLDING_FRACTION and fo > fr and gain < own * sr:
                    return False
                # a small ratio, where r is not smoother by MIN_ROUGHNESS_DIFFERENCE
                return gain >= np.log(MIN_SPECIFICITY_RATIO) or so - sr >= MIN_ROUGHNESS_DIFFERENCE
            # in 2D, against one that does not deform locally (affine), its own rate, for one
            # folding less than 1%, and at least the small-ratio floor
            against_linear = dimension == 2 and deforms_locally(r) and not deforms_locally(o)
            if by_spec == r and against_linear and fr < NO_FOLDING_FRACTION:
                floor = max(
                    SPECIFICITY_DECIDES_AGAINST_LINEAR * rougher, np.log(MIN_SPECIFICITY_RATIO)
                )
                if gain >= floor:
                    return True
            return too_little(r, o)
        pr, po = scores[r].overlap["inverse_volume"], scores[o].overlap["inverse_volume"]
        gain = np.log((pr / (1 - pr)) / (po / (1 - po)))
        fr, fo = scores[r].plausibility.folded_fraction, scores[o].plausibility.folded_fraction
        # against a registration that does not deform locally (affine), a lower rate
        linear = deforms_locally(r) and not deforms_locally(o)
        rate = OVERLAP_RATE_AGAINST_LINEAR if linear else OVERLAP_EXCHANGE_RATE
        # as for specificity, r charged by its own SDlogJ against one that folds, except in
        # 2D (where on the tuning splits the overlap's preference against folds was always
        # right); against one folding 2.5% or more at a lower rate
        own = 0.0
        if fo >= NO_FOLDING_FRACTION and fo > fr and dimension != 2:
            folds_rate = OVERLAP_RATE_AGAINST_FOLDS if fo >= CLEARLY_FOLDS_FRACTION else rate
            own = folds_rate * scores[r].plausibility.sdlogj
        return by_overlap == r and gain >= rate * rougher and gain >= own and not scores[r].flags

    out = []
    pw, pl = scores[w].plausibility, scores[l].plausibility
    if pl.folded_fraction >= SEVERE_FOLDED_FRACTION and pw.folded_fraction < NO_FOLDING_FRACTION:
        out.append("severe folding")
    against = evidence("specificity", l) or evidence("overlap", l)
    if evidence("specificity", w) and not against:
        out.append("specificity")
    if evidence("overlap", w) and not against:
        out.append("overlap")
    return out


# Drawn anew on every run; the examples are restatement mismatches that draws found only now
# and then (at 80 draws a run, 0 of 6 runs found the first): a lean against affine within
# one family in 2D, the overlap's preference against folds in 2D, and specificity's rate
# across families (the restatement without it failed on this draw).
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@example(seed=26772, n=4, noise=0.01, p_flag=0.0, labels=False, confidence=True, dimension=2)
@example(seed=375, n=2, noise=0.01, p_flag=0.0, labels=True, confidence=True, dimension=2)
@example(seed=167, n=5, noise=0.01, p_flag=0.0, labels=False, confidence=True, dimension=2)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 6),
    noise=st.sampled_from([0.01, 0.3, 3.0]),
    p_flag=st.sampled_from([0.0, 0.3, 1.0]),
    labels=st.booleans(),
    confidence=st.booleans(),
    dimension=st.sampled_from([2, 3, None]),
)
def test_decisions_follow_the_rules_and_every_other_pair_is_open(
    cheat_case, seed, n, noise, p_flag, labels, confidence, dimension
):
    """A pair is decided exactly when one of the verdict's rules allows it (restated here
    from the documentation), in that rule's direction, never both ways; the ranking puts the
    better of every decided pair first and the best are the registrations no other is
    decided better than."""
    _, result = cheat_case
    base = result.scores["truth"]
    rng = np.random.default_rng(seed)
    names = [f"r{i}" for i in range(n)]
    spec = dict(zip(names, np.round(rng.uniform(1, 3, n), 1), strict=True))  # some ties
    overlap = dict(zip(names, np.round(rng.uniform(0.3, 0.9, n), 2), strict=True))
    n_groups = 6
    # mostly one family, so that the smoother-fields rule is exercised; some of another
    # family and some unknown, where it must not decide
    families = [("fluid", "simpleitk")] * 3 + [("pairwise", "elastix"), None]
    # half the 3% folds become 1.5%, below CLEARLY_FOLDS_FRACTION; drawn from a stream of
    # their own, so the examples above draw what they drew when they were found
    mild = np.random.default_rng([seed, 1]).random(n) < 0.5
    scores = {}
    for i, k in enumerate(names):
        sdlogj = float(rng.choice([0.0, 0.1, 0.2, 0.5, 1.5]))
        folds = float(rng.choice([0.0, 0.0, 0.005, 0.03, 0.2]))
        plaus = dataclasses.replace(
            base.plausibility,
            sdlogj=sdlogj,
            folded_fraction=0.015 if folds == 0.03 and mild[i] else folds,
        )
        subjects = base.subjects
        if rng.random() < 0.25:  # affine: no local deformation, flat fields, no folds
            plaus = dataclasses.replace(plaus, sdlogj=0.0, folded_fraction=0.0)
            subjects = tuple(
                dataclasses.replace(q, deformation={**q.deformation, "nonlinear_rms_mm": 0.0})
                for q in base.subjects
            )
        scores[k] = dataclasses.replace(
            base,
            name=k,
            specificity=dataclasses.replace(base.specificity, value=float(spec[k])),
            overlap={**base.overlap, "inverse_volume": float(overlap[k])},
            plausibility=plaus,
            flags=("0.2% of voxels fold (test)",) if rng.random() < p_flag else (),
            family=families[rng.integers(len(families))],
            subjects=subjects,
        )
    comparisons = []
    if confidence:
        for measure, values in (("specificity", spec), ("overlap.inverse_volume", overlap)):
            scale = noise if measure == "specificity" else noise / 10
            reps = {k: v + scale * rng.standard_normal(n_groups) for k, v in values.items()}
            comparisons += compare(measure, values, reps)
    v = verdict(scores, comparisons, has_labels=labels, dimension=dimension)

    pairs = [frozenset((d.better, d.worse)) for d in v.decisions]
    assert len(pairs) == len(set(pairs))  # no pair decided twice, so never both ways
    for a, b in itertools.combinations(names, 2):
        ab = _rules_allow(a, b, scores, comparisons, labels, dimension)
        ba = _rules_allow(b, a, scores, comparisons, labels, dimension)
        decided = [d for d in v.decisions if {d.better, d.worse} == {a, b}]
        if not ab and not ba:
            assert not decided, (a, b, decided)
            assert any({p.a, p.b} == {a, b} and p.reason for p in v.open_pairs)
        elif decided:
            d = decided[0]
            allowed = ab if d.better == a else ba
            assert any(d.basis.startswith(rule) for rule in allowed), (d, allowed)
        else:  # allowed, but withdrawn: it lies on a cycle of decisions
            (p,) = [p for p in v.open_pairs if {p.a, p.b} == {a, b}]
            assert p.reason.startswith("the evidence contradicts itself: "), p
    # the withdrawn decisions, as their reasons state them, and the kept ones: a decision is
    # withdrawn exactly when its worse one reaches its better one through the others
    withdrawn = [
        tuple(p.reason.split(": ", 1)[1].split(" by ")[0].split(" > "))
        for p in v.open_pairs
        if p.reason.startswith("the evidence contradicts itself")
    ]
    edges = {(d.better, d.worse) for d in v.decisions} | set(withdrawn)

    def reaches(x, y):
        seen, todo = set(), [x]
        while todo:
            node = todo.pop()
            for u, w in edges:
                if u == node and w not in seen:
                    seen.add(w)
                    todo.append(w)
        return y in seen

    assert all(reaches(worse, better) for better, worse in withdrawn)
    assert not any(reaches(d.worse, d.better) for d in v.decisions)
    undominated = {k for k in names if not any(d.worse == k for d in v.decisions)}
    assert set(v.best) == (undominated or set(names))
    for d in v.decisions:
        assert v.ranking.index(d.better) < v.ranking.index(d.worse)
        assert d.to_dict() == {"better": d.better, "worse": d.worse, "basis": d.basis}
    assert v.to_dict()["decisions"] == [d.to_dict() for d in v.decisions]
    assert len(v.decisions) + len(v.open_pairs) == n * (n - 1) // 2
    # a lean is one of the pair: across (unknown) families, or in LINEAR_DIMENSIONS to one that
    # deforms locally over one that does not (specificity against affine, whatever the family)
    for p in v.open_pairs:
        assert p.leans_to in (None, p.a, p.b)
        if p.leans_to is not None:
            other = p.b if p.leans_to == p.a else p.a
            against_linear = (
                dimension in LINEAR_DIMENSIONS
                and _deforms_locally(scores[p.leans_to])
                and not _deforms_locally(scores[other])
            )
            fa, fb = scores[p.a].family, scores[p.b].family
            assert against_linear or fa is None or fa != fb, p
    # every lean the text names is one of the open pairs', the registration leaned to first
    leaning = [p for p in v.open_pairs if p.leans_to is not None]
    named = [t for t in v.text if t.startswith("Leaning, not decided: ")]
    assert len(named) == (1 if leaning else 0)
    if leaning:
        listed = named[0].removeprefix("Leaning, not decided: ").removesuffix(".").split("; ")
        expected = [f"{p.leans_to} over {({p.a, p.b} - {p.leans_to}).pop()}" for p in leaning]
        assert listed[: len(expected[:6])] == expected[:6]
        assert listed[6:] == ([f"and {len(leaning) - 6} more"] if len(leaning) > 6 else [])


def test_two_registrations_of_equal_true_quality_are_left_open(tmp_path):
    """A null case: the truth composed with two different smooth perturbations of the same
    size. Neither is better; the verdict must not say one is."""
    from test_evaluate import image, smooth_field

    data = make_case(tmp_path)
    again = []
    for i in range(N_IMAGES):
        sitk.WriteImage(image(smooth_field(300 + i, 3.0)), str(tmp_path / f"pertb{i}.mha"))
        again.append([f"pertb{i}.mha", f"truth{i}_1Warp.nii.gz"])
    data["registrations"]["perturbed_again"] = {
        "reference": "template.nii.gz",
        "transforms": again,
    }
    manifest = tmp_path / "manifest.yaml"
    manifest.write_text(yaml.safe_dump(data, sort_keys=False))
    result = nr.evaluate(manifest, **KW)
    v = result.verdict
    pair = {"perturbed", "perturbed_again"}
    assert not [d for d in v.decisions if {d.better, d.worse} == pair]
    assert [p for p in v.open_pairs if {p.a, p.b} == pair]
    # while the truth is decided better than both
    decided = {(d.better, d.worse) for d in v.decisions}
    assert {("truth", "perturbed"), ("truth", "perturbed_again")} <= decided


def test_decisions_that_go_round_are_withdrawn(cheat_case):
    """a > b by severe folding, b > c by the overlap and c > a by specificity: one of them
    is wrong and the data do not say which, so none of the three is asserted. (Specificity
    alone cannot make b > c here: b clearly folds, and more than c, since FRESH23.)"""
    _, result = cheat_case
    base = result.scores["truth"]

    scores = {  # a: the worst specificity, does not fold; b: folds 20% (severe); c: 2%
        "a": _registration(base, "a", spec=3.0, overlap=0.5, folded=0.0),
        "b": _registration(base, "b", spec=1.0, overlap=0.7, folded=0.2),
        "c": _registration(base, "c", spec=2.0, overlap=0.5, folded=0.02),
    }
    spec = {k: s.specificity.value for k, s in scores.items()}
    overlap = {k: s.overlap["inverse_volume"] for k, s in scores.items()}
    comparisons = _separable_where(spec, [{"a", "c"}]) + _separable_where(
        overlap, [{"b", "c"}], "overlap.inverse_volume"
    )
    v = verdict(scores, comparisons, has_labels=True)
    assert v.decisions == ()
    reasons = {frozenset((p.a, p.b)): p.reason for p in v.open_pairs}
    assert all(r.startswith("the evidence contradicts itself") for r in reasons.values())
    assert set(v.best) == {"a", "b", "c"}


def test_a_preference_that_roughness_buys_is_no_evidence_against_the_other_measure(cheat_case):
    """Specificity separably prefers `rough` (fields rougher by 0.5 SDlogJ), the overlap
    separably prefers `smooth`. A specificity advantage smaller than exp(EXCHANGE_RATE * 0.5)
    is what roughness alone can buy (the demons sweeps of the known-truth benchmark): it does
    not count, so the overlap decides for `smooth`. An advantage beyond that counts, and the
    two measures disagree: the pair stays open."""
    from itk_nrreval.measures.verdict import EXCHANGE_RATE

    _, result = cheat_case
    base = result.scores["truth"]

    def reg(name, spec, overlap, sdlogj):
        plaus = dataclasses.replace(base.plausibility, folded_fraction=0.0, sdlogj=sdlogj)
        return dataclasses.replace(
            base,
            name=name,
            specificity=dataclasses.replace(base.specificity, value=spec),
            overlap={**base.overlap, "inverse_volume": overlap},
            plausibility=plaus,
            flags=(),
        )

    bought = np.exp(EXCHANGE_RATE * 0.5)  # the specificity ratio 0.5 rougher fields can buy
    for ratio, decided in ((0.5 * bought, True), (2.0 * bought, False)):
        scores = {
            "smooth": reg("smooth", 2.0, 0.7, 0.2),
            "rough": reg("rough", 2.0 / ratio, 0.6, 0.7),
        }
        comparisons = []
        for measure, values in (
            ("specificity", {k: s.specificity.value for k, s in scores.items()}),
            ("overlap.inverse_volume", {k: s.overlap["inverse_volume"] for k, s in scores.items()}),
        ):
            reps = {k: v + 1e-3 * np.arange(6) for k, v in values.items()}  # separable
            comparisons += compare(measure, values, reps)
        v = verdict(scores, comparisons, has_labels=True)
        if decided:
            (d,) = v.decisions
            assert (d.better, d.worse) == ("smooth", "rough")
            assert d.basis.startswith("overlap (")
            assert "rough's lower specificity comes with fields 3.5x rougher" in d.basis
            assert v.best == ("smooth",) and v.decided
        else:
            assert v.decisions == ()
            (p,) = v.open_pairs
            assert p.reason == "specificity prefers rough, overlap prefers smooth"


# ----------------------------------------------------------------------------- issue 44


def _registration(
    base,
    name,
    *,
    spec,
    overlap=0.5,
    sdlogj=0.1,
    folded=0.0,
    n_samples=None,
    family=("fluid", "simpleitk"),
):
    """`base` (a real registration's scores) with these numbers, of one family unless said
    (the smoother-fields rule and the description length compare only within one)."""
    specificity = dataclasses.replace(base.specificity, value=float(spec))
    if n_samples is not None:
        specificity = dataclasses.replace(specificity, n_samples=int(n_samples))
    return dataclasses.replace(
        base,
        name=name,
        specificity=specificity,
        overlap={**base.overlap, "inverse_volume": float(overlap)},
        plausibility=dataclasses.replace(
            base.plausibility, sdlogj=float(sdlogj), folded_fraction=float(folded)
        ),
        flags=(),
        family=family,
    )


def _separable_where(values, pairs, measure="specificity"):
    """Comparisons of `values` (a dict) in which exactly the unordered `pairs` are
    separable: the jackknife replicates of every registration share one set of subject
    effects, and a registration of a separable pair gets a small effect of its own."""
    names = list(values)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            spread = 1e-3 * np.arange(6) if {a, b} in pairs else np.array([1, -1, 1, -1, 1, -1])
            reps = {a: values[a] + spread, b: values[b] + 0.0 * spread}
            out += compare(measure, {a: values[a], b: values[b]}, reps)
    return out


def _specificity_verdict(scores, separable, *, dimension=None):
    """The verdict without labels on `scores`, whose specificity differences are separable in
    exactly the pair `separable` (a set of two names) and no other."""
    values = {k: s.specificity.value for k, s in scores.items()}
    comparisons = _separable_where(values, [separable])
    return verdict(scores, comparisons, has_labels=False, dimension=dimension)


def _odds(p: float) -> float:
    """The odds of an overlap `p`, as the verdict's overlap rates read it."""
    return p / (1 - p)


def _overlap_verdict(scores, separable, *, dimension=None):
    """The verdict with labels on `scores`, whose overlap differences are separable in
    exactly the pair `separable` (a set of two names) and no other; no specificity
    comparison."""
    overlaps = {k: s.overlap["inverse_volume"] for k, s in scores.items()}
    comparisons = _separable_where(overlaps, [separable], "overlap.inverse_volume")
    return verdict(scores, comparisons, has_labels=True, dimension=dimension)


def test_too_few_samples_decide_nothing_and_the_text_says_so(cheat_case, tmp_path):
    """--samples 2 is legal for a quick try, but the verdict decides no pair (the same data
    at M = 3000 decide the truth best), every pair open with the reason, and the verdict's
    first sentence -- the head of summary.md and of the report -- says so."""
    manifest, converged = cheat_case
    assert converged.verdict.decided and converged.verdict.decisions  # at M = 3000
    with pytest.warns(RuntimeWarning, match="flagged as implausible"):
        result = nr.evaluate(manifest, n_samples=2, seed=2, progress=False)
    v = result.verdict
    assert v.decisions == () and not v.decided
    from itk_nrreval.measures.verdict import MIN_SAMPLES

    names = list(result.scores)
    reason = (
        f"M = 2 samples is below the minimum of {MIN_SAMPLES:,} for a verdict: the scores "
        "have not converged"
    )
    assert len(v.open_pairs) == len(names) * (len(names) - 1) // 2
    assert {p.reason for p in v.open_pairs} == {reason}
    assert v.text[0].startswith(f"Not decided: {reason}")
    assert set(v.best) == set(names)  # none decided better than another
    result.write(tmp_path / "out", figures=False)
    summary = (tmp_path / "out" / "summary.md").read_text()
    assert summary.startswith(v.text[0])
    # the same scores with M at the minimum are judged by the rules again
    base = converged.scores
    for m, decides in ((MIN_SAMPLES - 1, False), (MIN_SAMPLES, True)):
        scores = {
            n: dataclasses.replace(s, specificity=dataclasses.replace(s.specificity, n_samples=m))
            for n, s in base.items()
        }
        again = verdict(scores, converged.comparisons, has_labels=True, dimension=2)  # as evaluate
        assert bool(again.decisions) == decides
        if decides:
            assert again == converged.verdict


def test_best_is_said_by_the_measures_that_decided_it_over_each_other(cheat_case):
    """top is decided better than `b` by specificity alone and than `c` by overlap alone:
    "by overlap and specificity" would claim what neither measure showed on its own."""
    _, result = cheat_case
    base = result.scores["truth"]
    scores = {
        "top": _registration(base, "top", spec=1.0, overlap=0.8),
        "b": _registration(base, "b", spec=2.0, overlap=0.8),
        "c": _registration(base, "c", spec=1.0 + 1e-9, overlap=0.5),
    }
    spec = {k: s.specificity.value for k, s in scores.items()}
    over = {k: s.overlap["inverse_volume"] for k, s in scores.items()}
    comparisons = _separable_where(spec, [{"top", "b"}]) + _separable_where(
        over, [{"top", "c"}], "overlap.inverse_volume"
    )
    v = verdict(scores, comparisons, has_labels=True)
    basis = {d.worse: d.basis.split(" (")[0] for d in v.decisions if d.better == "top"}
    assert basis == {"b": "specificity", "c": "overlap"}
    assert v.decided
    assert v.text[0] == (
        "top is best: decided better than every other registration "
        "(by specificity over b; by overlap over c)."
    )


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 7),
    p_separable=st.sampled_from([0.3, 0.6, 0.9]),
)
def test_the_verdicts_order_extends_the_decisions_and_is_said_as_it_is(
    cheat_case, seed, n, p_separable
):
    """The ranking puts the better of every decided pair first, and otherwise the lower
    specificity: a registration is listed above one with a lower specificity only when a
    registration between them (or itself) is decided better than that one -- the order
    is what the decisions force and the tie-break says, nothing else. When one
    registration is decided best, the measures its sentence names decided it over every
    other registration."""
    _, result = cheat_case
    base = result.scores["truth"]
    rng = np.random.default_rng(seed)
    names = [f"r{i}" for i in range(n)]
    scores = {
        k: _registration(
            base,
            k,
            spec=round(float(rng.uniform(1, 3)), 1),
            overlap=round(float(rng.uniform(0.3, 0.9)), 2),
            sdlogj=float(rng.choice([0.1, 0.1, 0.3])),
            folded=float(rng.choice([0.0, 0.0, 0.0, 0.2])),
        )
        for k in names
    }
    pairs = [set(p) for p in itertools.combinations(names, 2) if rng.random() < p_separable]
    spec = {k: s.specificity.value for k, s in scores.items()}
    over = {k: s.overlap["inverse_volume"] for k, s in scores.items()}
    pairs_o = [set(p) for p in itertools.combinations(names, 2) if rng.random() < p_separable]
    comparisons = _separable_where(spec, pairs) + _separable_where(
        over, pairs_o, "overlap.inverse_volume"
    )
    v = verdict(scores, comparisons, has_labels=True)
    order = list(v.ranking)
    assert sorted(order) == sorted(names)
    decided = {(d.better, d.worse) for d in v.decisions}
    for i, a in enumerate(order):
        for j in range(i + 1, len(order)):
            b = order[j]
            assert (b, a) not in decided
            if (spec[a], names.index(a)) > (spec[b], names.index(b)):
                assert any((order[k], b) in decided for k in range(i, j)), (order, decided)
    if v.decided:
        top = v.best[0]
        clause = v.text[0].split("(", 1)[1].rstrip(").")
        mine = {
            d.worse: d.basis.split(" (")[0].split(" and ") for d in v.decisions if d.better == top
        }
        for part in clause.split("; "):
            words, _, over_whom = part.removeprefix("by ").partition(" over ")
            whom = over_whom.replace(" and ", ", ").split(", ") if over_whom else list(mine)
            for measure in words.split(" and "):
                assert all(measure in mine[w] for w in whom), (v.text[0], mine)


def test_an_order_of_levels_is_not_the_verdicts_order(cheat_case):
    """The case of the issue: `affine` (last in every measure) is decided worse than the
    best only; `near` waits for `mid`, which is decided better than it. Listed level by
    level, affine came above near; the verdict's order lists near first, and the reports
    and the demo's table use that one order."""
    _, result = cheat_case
    base = result.scores["truth"]
    spec = {"best": 1.0, "mid": 2.0, "near": 3.0, "affine": 4.0}
    scores = {k: _registration(base, k, spec=v) for k, v in spec.items()}
    comparisons = _separable_where(spec, [{"best", "mid"}, {"mid", "near"}, {"best", "affine"}])
    v = verdict(scores, comparisons, has_labels=False)
    assert {(d.better, d.worse) for d in v.decisions} == {
        ("best", "mid"),
        ("mid", "near"),
        ("best", "affine"),
    }
    assert v.ranking == ("best", "mid", "near", "affine")


def test_the_demo_table_and_the_summary_list_the_verdicts_order(cheat_case):
    """One order everywhere: the demo's table (its stdout) and summary.md list the
    registrations as verdict.ranking does, whatever the order of the manifest."""
    from itk_nrreval.experiments.demo import _table
    from itk_nrreval.report import summary_table

    _, result = cheat_case
    backwards = dict(reversed(list(result.scores.items())))  # the manifest's order reversed
    result = dataclasses.replace(result, scores=backwards)
    assert list(result.scores) != list(result.verdict.ranking)
    error = {n: float(k) for k, n in enumerate(result.scores)}

    def rows(table: str) -> list[str]:
        names = []
        for line in table.splitlines():
            cell = line.split("|")[1].strip() if line.startswith("| ") else ""
            name = cell.removesuffix(" (flagged)")
            if name in result.scores and name not in names:
                names.append(name)
        return names

    assert rows(_table(result, error)) == list(result.verdict.ranking)
    assert rows(summary_table(result)) == list(result.verdict.ranking)


def test_roughness_that_buys_too_little_decides_for_the_smoother(cheat_case):
    """Fields 0.4 rougher in SDlogJ must buy at least exp(SMOOTHNESS_RATE * 0.4) in
    specificity. Below it the smoother registration is decided better; between that and
    exp(EXCHANGE_RATE * 0.4) the pair is the trade-off's knee and stays open; beyond that the
    rougher one is; and nearly equal roughness never decides for the smoother."""
    from itk_nrreval.measures.verdict import EXCHANGE_RATE, SMOOTHNESS_RATE

    _, result = cheat_case
    base = result.scores["truth"]
    dr = 0.4
    low, high = np.exp(SMOOTHNESS_RATE * dr), np.exp(EXCHANGE_RATE * dr)

    def decided(ratio, rough_sdlogj=0.1 + dr):
        scores = {
            "smooth": _registration(base, "smooth", spec=10.0, sdlogj=0.1),
            "rough": _registration(base, "rough", spec=10.0 / ratio, sdlogj=rough_sdlogj),
        }
        v = _specificity_verdict(scores, {"smooth", "rough"})
        return [(d.better, d.worse, d.basis) for d in v.decisions], v

    # the intervals of _separable_where are a few thousandths wide: ratios stay clear of them
    for ratio in (0.9, 1.0, 1.1, 0.98 * low):
        [(better, worse, basis)], _ = decided(ratio)
        assert (better, worse) == ("smooth", "rough"), ratio
        if ratio > 1:
            assert "rough's fields are 0.40 rougher in SDlogJ" in basis
            assert f"less than the {low:.2f}x that much roughness must buy" in basis
    for ratio in (1.02 * low, np.sqrt(low * high), 0.98 * high):
        assert decided(ratio)[0] == [], ratio
    assert [d[:2] for d in decided(1.02 * high)[0]] == [("rough", "smooth")]
    # nearly equal roughness: the smoother is not preferred for that
    assert decided(1.1, rough_sdlogj=0.13)[0] == []
    # a registration without local deformation (affine: no non-linear displacement) is not
    # preferred for its smoothness: SDlogJ cannot see the deformation it leaves out. One
    # that does deform, however little its SDlogJ (over-smoothed demons), can be
    scores = {
        "affine": dataclasses.replace(
            _registration(base, "affine", spec=10.0, sdlogj=0.0),
            subjects=tuple(
                dataclasses.replace(q, deformation={**q.deformation, "nonlinear_rms_mm": 0.0})
                for q in base.subjects
            ),
        ),
        "rough": _registration(base, "rough", spec=10.0 / 1.1, sdlogj=dr),
    }
    v = _specificity_verdict(scores, {"affine", "rough"})
    assert v.decisions == ()
    scores["affine"] = _registration(base, "affine", spec=10.0, sdlogj=0.0)  # deforms
    v = _specificity_verdict(scores, {"affine", "rough"})
    assert [(d.better, d.worse) for d in v.decisions] == [("affine", "rough")]
    # nor one that folds more than the rougher one: folds are roughness that SDlogJ ranks
    # poorly (a B-spline folding 3% with SDlogJ 0.5 corresponded worse than demons at 1.0)
    # nor one that folds at all (1% or more), even less than the other: FRESH6's 25 mm
    # B-spline folding 4.4% corresponded worse than a 10 mm one folding 8.6%
    for folds, expected in ((0.03, ()), (0.0, ("smooth",)), (0.044, ()), (0.009, ("smooth",))):
        scores = {
            "smooth": _registration(base, "smooth", spec=10.0, sdlogj=0.1, folded=folds),
            "rough": _registration(base, "rough", spec=10.0 / 1.1, sdlogj=0.1 + dr, folded=0.086),
        }
        v = _specificity_verdict(scores, {"smooth", "rough"})
        assert tuple(d.better for d in v.decisions) == expected, folds


def test_specificity_is_no_evidence_against_folds_or_by_a_small_ratio(cheat_case):
    """Issue 41's held-out case outside the project, two wrong decisions, as numbers:

    - demons at 1 mm (SDlogJ 0.29, no folds) was decided better than a 25 mm B-spline that
      folds 2.3% (SDlogJ 0.54, inflated around its folds) on its separably lower
      specificity, against the truth. Against a registration that folds, specificity is
      evidence only beyond what the preferred registration's own roughness could buy
      (exp(EXCHANGE_RATE * 0.29) = 4.9x);
    - demons at 3 mm was decided better than a displacement-field registration at equal
      roughness (SDlogJ 0.09 and 0.09) on a 1.16x lower specificity, against the truth. A
      ratio below MIN_SPECIFICITY_RATIO decides nothing unless the preferred fields are
      clearly smoother.
    """
    from itk_nrreval.measures.verdict import EXCHANGE_RATE, MIN_SPECIFICITY_RATIO

    _, result = cheat_case
    base = result.scores["truth"]

    def decided(a, b):
        scores = {a.name: a, b.name: b}
        v = _specificity_verdict(scores, {a.name, b.name})
        return [(d.better, d.worse) for d in v.decisions], v

    # a registration that folds 2.3% against demons whose specificity is 1.3x lower
    bspline = _registration(base, "bspline", spec=13.0, sdlogj=0.54, folded=0.023)
    demons = _registration(base, "demons", spec=10.0, sdlogj=0.29)
    pairs, v = decided(demons, bspline)
    assert pairs == []
    (p,) = v.open_pairs
    assert "bspline folds 2.3% of its voxels" in p.reason
    assert f"less than the {np.exp(EXCHANGE_RATE * 0.29):.2f}x" in p.reason
    # beyond what demons' own roughness could buy, it decides
    far = _registration(base, "bspline", spec=10.0 * 1.02 * np.exp(EXCHANGE_RATE * 0.29),
                        sdlogj=0.54, folded=0.023)  # fmt: skip
    assert decided(demons, far)[0] == [("demons", "bspline")]
    # against one that folds less than NO_FOLDING_FRACTION, as before
    little = _registration(base, "bspline", spec=13.0, sdlogj=0.54, folded=0.005)
    assert decided(demons, little)[0] == [("demons", "bspline")]

    # equal roughness: 1.16x decides nothing, 1.25x does
    field = _registration(base, "field", spec=11.6, sdlogj=0.09)
    demons3 = _registration(base, "demons", spec=10.0, sdlogj=0.09)
    pairs, v = decided(demons3, field)
    assert pairs == [] and f"below the {MIN_SPECIFICITY_RATIO:g}x" in v.open_pairs[0].reason
    field = _registration(base, "field", spec=12.5, sdlogj=0.09)
    assert decided(demons3, field)[0] == [("demons", "field")]
    # clearly smoother (by 0.06 >= MIN_ROUGHNESS_DIFFERENCE): a small ratio is evidence
    field = _registration(base, "field", spec=11.6, sdlogj=0.15)
    assert decided(demons3, field)[0] == [("demons", "field")]


def test_the_overlap_is_no_evidence_against_folds_in_3d(cheat_case):
    """The benchmark's FRESH5 (declared before it ran): in 3D, demons at 2 mm (SDlogJ 0.47)
    was decided better than a 10 mm B-spline that folds 1.7% (SDlogJ 0.64) and corresponds
    better, by the overlap's separable 1.61x odds. Against a registration that folds, the
    overlap too is evidence only beyond exp(OVERLAP_EXCHANGE_RATE * 0.47) = 6.9x, in 3D and
    where the dimension is unknown. In 2D (OVERLAP_AGAINST_FOLDS_DIMENSIONS) it is evidence,
    while specificity's preference there is still charged."""
    from itk_nrreval.measures.verdict import OVERLAP_AGAINST_FOLDS_DIMENSIONS, OVERLAP_EXCHANGE_RATE

    assert OVERLAP_AGAINST_FOLDS_DIMENSIONS == (2,)
    _, result = cheat_case
    base = result.scores["truth"]

    def decided(bspline_overlap, dimension):
        scores = {
            "demons": _registration(base, "demons", spec=10.0, overlap=0.6, sdlogj=0.47),
            "bspline": _registration(
                base, "bspline", spec=10.0, overlap=bspline_overlap, sdlogj=0.64, folded=0.017
            ),
        }
        v = _overlap_verdict(scores, {"demons", "bspline"}, dimension=dimension)
        return [(d.better, d.worse) for d in v.decisions], v

    bar = np.exp(OVERLAP_EXCHANGE_RATE * 0.47)
    at_161 = _odds(0.6) / 1.61  # the bspline's odds at FRESH5's ratio
    for dimension in (3, None):
        pairs, v = decided(at_161 / (1 + at_161), dimension)
        assert pairs == []
        assert "bspline folds 1.7% of its voxels" in v.open_pairs[0].reason
        assert f"1.61x the odds of overlap is less than the {bar:.2f}x" in v.open_pairs[0].reason
        beyond = _odds(0.6) / (1.02 * bar)
        assert decided(beyond / (1 + beyond), dimension)[0] == [("demons", "bspline")]
    pairs, v = decided(at_161 / (1 + at_161), 2)
    assert pairs == [("demons", "bspline")]
    assert "1.61x the odds of overlap" in v.decisions[0].basis
    # specificity's preference in the same pair (1.61x, no labels) is charged in 2D as well
    scores = {
        "demons": _registration(base, "demons", spec=10.0, overlap=0.6, sdlogj=0.47),
        "bspline": _registration(
            base, "bspline", spec=16.1, overlap=0.6, sdlogj=0.64, folded=0.017
        ),
    }
    v = _specificity_verdict(scores, {"demons", "bspline"}, dimension=2)
    assert v.decisions == ()
    assert "bspline folds 1.7% of its voxels" in v.open_pairs[0].reason


def test_specificity_never_decides_for_the_registration_that_folds_more(cheat_case):
    """FRESH23 (declared before it ran): on the second scan of families_phantom2d_fold_s114,
    a 10 mm B-spline folding 10.9% (SDlogJ 0.99; true error 7.84 mm) was decided better
    than demons at 0.1 mm field smoothing folding 3.4% (SDlogJ 2.43; 6.34 mm) by a 1.24x
    lower specificity, with and without labels: SDlogJ, over the voxels that do not fold,
    called the B-spline's fields the smoother, and no charge looked at its folds. Where the
    preferred registration clearly folds (CLEARLY_FOLDS_FRACTION, 2.5%) and more than the
    other, its preference is no evidence, however large, in every dimension; folding no more
    than the other, or less than 2.5%, it is."""
    _, result = cheat_case
    base = result.scores["truth"]

    def by_specificity(ratio, folds_more, dimension, demons_folds=0.034):
        scores = {
            "demons": _registration(base, "demons", spec=10.0, sdlogj=2.43, folded=demons_folds),
            "bspline": _registration(
                base,
                "bspline",
                spec=10.0 / ratio,
                sdlogj=0.99,
                folded=folds_more,
                family=("pairwise", "elastix"),
            ),
        }
        v = _specificity_verdict(scores, {"demons", "bspline"}, dimension=dimension)
        return [(d.better, d.worse) for d in v.decisions], v

    for dimension in (2, 3, None):
        for ratio in (1.24, 3.0):
            pairs, v = by_specificity(ratio, 0.109, dimension)
            assert pairs == [], (ratio, dimension)
            assert "bspline folds 10.9% of its voxels, more than demons (3.4%)" in (
                v.open_pairs[0].reason
            )
        # folding less than the other, the same preference still counts (at 3x; FRESH23's
        # 1.24x is below what its rates ask there); and folding more, but less than 2.5%
        assert by_specificity(3.0, 0.02, dimension)[0] == [("bspline", "demons")]
        assert by_specificity(3.0, 0.02, dimension, 0.005)[0] == [("bspline", "demons")]


def test_against_a_registration_that_clearly_folds_the_charge_is_lower(cheat_case):
    """Against a registration folding at least CLEARLY_FOLDS_FRACTION (2.5%), specificity's
    preference counts from exp(SPECIFICITY_RATE_AGAINST_FOLDS s) and, in 3D, the overlap's
    from exp(OVERLAP_RATE_AGAINST_FOLDS s), s the preferred registration's own SDlogJ; below
    2.5% the exchange rates stay. The pair that set both rates, the benchmark's FRESH5
    (demons at 2 mm, SDlogJ 0.47, over a 10 mm B-spline folding 1.7% that corresponded
    better: 1.19x lower specificity on the second scan, ln / s = 0.37; 1.61x the odds of
    overlap, 1.02), stays open even were the B-spline folding 3%; and a B-spline folding 2.3%
    (issue 41's outside case, where demons at 1 mm were decided wrong by specificity) keeps
    the exchange rate."""
    from itk_nrreval.measures.verdict import (
        CLEARLY_FOLDS_FRACTION,
        EXCHANGE_RATE,
        OVERLAP_EXCHANGE_RATE,
        OVERLAP_RATE_AGAINST_FOLDS,
        SPECIFICITY_RATE_AGAINST_FOLDS,
    )

    assert CLEARLY_FOLDS_FRACTION == 0.025
    _, result = cheat_case
    base = result.scores["truth"]
    s = 0.47

    def by_specificity(ratio, folds, dimension=3):
        scores = {
            "demons": _registration(base, "demons", spec=10.0, sdlogj=s),
            "bspline": _registration(base, "bspline", spec=10.0 * ratio, sdlogj=0.64, folded=folds),
        }
        v = _specificity_verdict(scores, {"demons", "bspline"}, dimension=dimension)
        return [(d.better, d.worse) for d in v.decisions], v

    bar = np.exp(SPECIFICITY_RATE_AGAINST_FOLDS * s)
    assert 1.19 < bar < 1.02 * bar < np.exp(EXCHANGE_RATE * s)
    for folds in (0.017, 0.023, 0.03):
        assert by_specificity(1.19, folds)[0] == []  # FRESH5's pair, however much it folds
    for dimension in (2, 3, None):  # specificity's rate holds in every dimension
        pairs, v = by_specificity(0.98 * bar, 0.03, dimension)
        assert pairs == []
        assert (
            f"less than the {bar:.2f}x its own roughness could buy (against one folding 2.5%"
            in (v.open_pairs[0].reason)
        )
        assert by_specificity(1.02 * bar, 0.03, dimension)[0] == [("demons", "bspline")]
    for folds in (0.017, 0.023):  # below 2.5%: still the exchange rate
        pairs, v = by_specificity(1.02 * bar, folds)
        assert pairs == []
        assert f"less than the {np.exp(EXCHANGE_RATE * s):.2f}x its own roughness could buy" in (
            v.open_pairs[0].reason
        )

    def by_overlap(ratio, folds, dimension=3):
        """demons' overlap 0.6, the B-spline's at `ratio` lower odds; equal specificity."""
        o = _odds(0.6) / ratio
        scores = {
            "demons": _registration(base, "demons", spec=10.0, overlap=0.6, sdlogj=s),
            "bspline": _registration(
                base, "bspline", spec=10.0, overlap=o / (1 + o), sdlogj=0.64, folded=folds
            ),
        }
        v = _overlap_verdict(scores, {"demons", "bspline"}, dimension=dimension)
        return [(d.better, d.worse) for d in v.decisions]

    bar = np.exp(OVERLAP_RATE_AGAINST_FOLDS * s)
    assert 1.61 < bar < 1.02 * bar < np.exp(OVERLAP_EXCHANGE_RATE * s)
    for dimension in (3, None):
        assert by_overlap(1.61, 0.03, dimension) == []
        assert by_overlap(0.98 * bar, 0.03, dimension) == []
        assert by_overlap(1.02 * bar, 0.03, dimension) == [("demons", "bspline")]
        assert by_overlap(1.02 * bar, 0.017, dimension) == []  # exchange rate below 2.5%
    assert by_overlap(1.61, 0.017, 2) == [("demons", "bspline")]  # 2D: not charged at all


def test_the_common_smoothness_benchmark_wraps_todays_verdict(cheat_case):
    """benchmarks/bench_common_smoothness.py (a measure tried and not kept) adds its evidence
    by wrapping the verdict's smoother-fields step. The wrapper must take what the verdict
    passes: it raised a TypeError once the step took a `dimension` keyword, so the
    benchmark could not run."""
    from _benchmarks import benchmark_module

    bench = benchmark_module("bench_common_smoothness")
    _, result = cheat_case
    base = result.scores["truth"]
    scores = {n: _registration(base, n, spec=10.0, sdlogj=0.3) for n in ("a", "b")}
    smoothed = {"a": 10.0, "b": 13.0}  # 1.3x lower at a common smoothness, neither folds
    with bench._with_rule("v1", smoothed):
        v = _specificity_verdict(scores, set(), dimension=2)  # specificity not separable
    assert [(d.better, d.worse) for d in v.decisions] == [("a", "b")]
    assert v.decisions[0].basis.startswith("specificity at a common smoothness")
    assert _specificity_verdict(scores, set(), dimension=2).decisions == ()  # unwrapped again


def _affine(base, *, spec):
    """An affine registration "affine" (overlap 0.5, SDlogJ 0): `base`'s scores with every
    subject's non-linear displacement 0, so it does not deform locally."""
    affine = _registration(base, "affine", spec=spec, overlap=0.5, sdlogj=0.0)
    return dataclasses.replace(
        affine,
        subjects=tuple(
            dataclasses.replace(q, deformation={**q.deformation, "nonlinear_rms_mm": 0.0})
            for q in base.subjects
        ),
        family=("affine", "simpleitk"),
    )


@pytest.mark.parametrize(("sdlogj", "odds_ratio", "decided"), [
    (0.35, 2.76, True),  # families_mni2d's 2 mm demons over affine (1.72 vs 2.74 mm)
    (0.71, 2.42, False),  # its 1 mm demons, which the truth put behind affine (3.07 mm)
])  # fmt: skip
def test_the_overlap_against_affine_is_charged_at_its_own_rate(
    cheat_case, sdlogj, odds_ratio, decided
):
    """Against a registration that does not deform locally (affine), SDlogJ is all of the
    other's local deformation, so the overlap's odds must beat exp(OVERLAP_RATE_AGAINST_LINEAR
    x SDlogJ), not exp(OVERLAP_EXCHANGE_RATE x SDlogJ). The benchmark's tuning pairs: the
    2 mm demons' 2.76x odds over affine is evidence (it was not at the exchange rate, 4.2x);
    the 1 mm demons' 2.42x for fields twice as rough is not. Between two deformable
    registrations the same numbers are charged at the exchange rate, as before."""
    from itk_nrreval.measures.verdict import OVERLAP_EXCHANGE_RATE, OVERLAP_RATE_AGAINST_LINEAR

    _, result = cheat_case
    base = result.scores["truth"]
    affine = _affine(base, spec=10.0)
    p = odds_ratio / (1 + odds_ratio)  # odds 1 for affine's 0.5
    demons = _registration(base, "demons", spec=10.0, overlap=p, sdlogj=sdlogj)
    assert np.exp(OVERLAP_EXCHANGE_RATE * sdlogj) > odds_ratio  # open at the exchange rate
    assert (np.exp(OVERLAP_RATE_AGAINST_LINEAR * sdlogj) < odds_ratio) == decided
    for other, expected in ((affine, decided), (_registration(base, "affine", spec=10.0,
                            overlap=0.5, sdlogj=0.0), False)):  # fmt: skip
        scores = {"demons": demons, "affine": other}
        v = _overlap_verdict(scores, {"demons", "affine"})
        pairs = [(d.better, d.worse) for d in v.decisions]
        # the second "affine" deforms locally (the truth's subjects): the exchange rate
        assert pairs == ([("demons", "affine")] if expected else []), (other.subjects[1], pairs)
        if expected:
            assert v.decisions[0].basis.startswith("overlap")
            assert "affine does not deform locally" in v.decisions[0].basis


@pytest.mark.parametrize(("sdlogj", "ratio", "outcome"), [
    (0.35, 2.64, "decided"),  # families_mni2d's 2 mm demons over affine (1.72 vs 2.74 mm)
    (0.41, 2.48, "leans"),  # FRESH6's 2 mm demons, which the truth put behind affine
    (0.71, 3.06, "open"),  # families_mni2d's 1 mm demons, also behind affine (3.07 mm)
])  # fmt: skip
def test_specificity_against_affine_decides_and_leans_at_its_own_rates(
    cheat_case, sdlogj, ratio, outcome
):
    """Without labels, against a registration that does not deform locally (affine), a
    specificity lower by exp(SPECIFICITY_DECIDES_AGAINST_LINEAR x SDlogJ) decides for the
    deformable registration, and one lower by exp(SPECIFICITY_RATE_AGAINST_LINEAR x SDlogJ)
    only leans to it, though both are below exp(EXCHANGE_RATE x SDlogJ): the 2 mm demons'
    2.64x lower specificity than affine decides; FRESH6's 2.48x for SDlogJ 0.41, where the
    truth says affine corresponded better, leans; the 1 mm demons' 3.06x for fields twice as
    rough does neither. Against a registration that deforms locally, in 3D, and where the
    dimension is unknown, it decides nothing and leans nowhere. The numbers are the
    benchmark's own (2D)."""
    from itk_nrreval.measures.verdict import (
        EXCHANGE_RATE,
        SPECIFICITY_DECIDES_AGAINST_LINEAR,
        SPECIFICITY_RATE_AGAINST_LINEAR,
    )

    _, result = cheat_case
    base = result.scores["truth"]
    rigid = _affine(base, spec=10.0 * ratio)
    demons = _registration(base, "demons", spec=10.0, overlap=0.5, sdlogj=sdlogj)
    assert np.exp(EXCHANGE_RATE * sdlogj) > ratio  # not decided at the exchange rate
    # the numbers are on the side of each rate that the outcome says
    assert (np.exp(SPECIFICITY_DECIDES_AGAINST_LINEAR * sdlogj) <= ratio) == (outcome == "decided")
    assert (np.exp(SPECIFICITY_RATE_AGAINST_LINEAR * sdlogj) < ratio) == (outcome != "open")
    deforming = _registration(base, "affine", spec=10.0 * ratio, overlap=0.5, sdlogj=0.0)
    for other, dimension, expected in (
        (rigid, 2, outcome),
        (rigid, 3, "open"),  # set on 2D cases alone, and used only there
        (rigid, None, "open"),
        (deforming, 2, "open"),
    ):
        scores = {"demons": demons, "affine": other}
        v = _specificity_verdict(scores, {"demons", "affine"}, dimension=dimension)
        decided = [(d.better, d.worse) for d in v.decisions]
        assert (decided == [("demons", "affine")]) == (expected == "decided"), (dimension, v)
        pairs = [p for p in v.open_pairs if {p.a, p.b} == {"demons", "affine"}]
        assert any(p.leans_to == "demons" for p in pairs) == (expected == "leans"), dimension
        if expected == "decided":
            basis = v.decisions[0].basis
            assert basis.startswith("specificity (")
            assert "affine does not deform locally" in basis
            assert f"its {ratio:.2f}x lower specificity reaches the" in basis
        if expected == "leans":
            (pair,) = pairs
            assert "affine does not deform locally" in pair.reason
            assert f"its {ratio:.2f}x lower specificity is more than the" in pair.reason
            assert "so it leans to demons" in pair.reason
            assert any(t.startswith("Leaning, not decided: demons over affine") for t in v.text)


@pytest.mark.parametrize(("sdlogj", "ratio", "folded", "dimension", "affine_better"), [
    # families_mni2d_s2's demons at 0.5 mm: 3.50x lower specificity than affine for SDlogJ
    # 1.41 (ln 3.50 / 1.41 = 0.89), and a worse true error (3.84 against 2.74 mm)
    (1.411, 3.50, 0.0, 2, True),
    (1.411, 3.50, 0.0, 3, False),  # set on 2D cases alone, and used only there
    (1.411, 3.50, 0.0, None, False),
    (1.411, 3.50, 0.023, 2, False),  # folds: its SDlogJ understates what it bought
    # families_mni2d_s2's demons at 1 mm: ln 3.08 / 0.83 = 1.35, above the rate
    (0.833, 3.08, 0.0, 2, False),
])  # fmt: skip
def test_affine_is_decided_better_where_the_deformation_bought_too_little(
    cheat_case, sdlogj, ratio, folded, dimension, affine_better
):
    """The converse of specificity against affine: in 2D, where a registration that deforms
    locally and does not fold has a specificity advantage over an affine registration that,
    at the top of its interval, is below exp(SMOOTHNESS_RATE_AGAINST_LINEAR x SDlogJ), the
    affine registration is decided better; its SDlogJ is all of its local deformation, and it
    bought too little to be correspondence. The numbers are the benchmark's own."""
    from itk_nrreval.measures.verdict import SMOOTHNESS_RATE_AGAINST_LINEAR

    _, result = cheat_case
    base = result.scores["truth"]
    rigid = _affine(base, spec=10.0 * ratio)
    demons = _registration(base, "demons", spec=10.0, overlap=0.5, sdlogj=sdlogj, folded=folded)
    assert (np.log(ratio) < SMOOTHNESS_RATE_AGAINST_LINEAR * sdlogj) == (
        affine_better or folded > 0 or dimension != 2
    )
    v = _specificity_verdict({"demons": demons, "affine": rigid}, {"demons", "affine"},
                             dimension=dimension)  # fmt: skip
    decided = [(d.better, d.worse) for d in v.decisions]
    if affine_better:
        assert decided == [("affine", "demons")]
        basis = v.decisions[0].basis
        assert basis.startswith("specificity (")
        assert "affine does not deform locally, so demons's SDlogJ is all of its" in basis
        too_little = np.exp(SMOOTHNESS_RATE_AGAINST_LINEAR * sdlogj)
        assert f"less than the {too_little:.2f}x that much roughness must buy" in basis
        assert v.best == ("affine",)
    else:
        assert decided == [], v
        assert v.open_pairs[0].leans_to is None


@pytest.mark.xfail(
    strict=True,
    reason="FRESH13, FRESH16, FRESH19 and FRESH20 (docs/verdict.md): the label overlap "
    "itself contradicts the truth here, and no rule of the verdict can tell; not fixed",
)
@pytest.mark.parametrize(("demons", "bspline"), [
    # FRESH13's families_phantom2d_syn_s50: 1.83 mm against 1.47 mm
    ((9.82, 0.7228, 0.184), (13.43, 0.6145, 0.124)),
    # FRESH16's families_phantom2d_syn_s71: 1.95 mm against 1.77 mm
    ((11.74, 0.7169, 0.187), (16.56, 0.6320, 0.121)),
    # FRESH19's families_phantom2d_syn_s87: 1.74 mm against 1.44 mm
    ((11.19, 0.7335, 0.189), (14.41, 0.6369, 0.110)),
    # FRESH20's families_phantom2d_syn_s98: 1.78 mm against 1.55 mm
    ((10.23, 0.7191, 0.184), (13.70, 0.6255, 0.121)),
])  # fmt: skip
def test_demons_over_a_coarse_bspline_by_the_overlap_stays_open(cheat_case, demons, bspline):
    """The benchmark's FRESH13, FRESH16, FRESH19 and FRESH20, each declared before it ran: on
    the phantom's FAMILIES_SYN cases the verdict decides demons at 3 mm (SDlogJ 0.18-0.19)
    better than a B-spline on a 40 mm grid (SDlogJ 0.11-0.12), which corresponds better, by
    the overlap's separable 1.64x, 1.47x, 1.57x and 1.53x odds, above the exp(4.1 dr) = 1.28x,
    1.31x, 1.38x and 1.30x their extra roughness could buy; specificity prefers demons too
    (1.37x, 1.41x, 1.29x and 1.34x, bought by roughness). Every measure points the wrong way:
    open would be the right answer. No rate set on the tuning splits leaves them open:
    ln(odds ratio) / dr is 8.2, 5.9, 5.7 and 6.8 here, and on the tuning splits the steepest
    such preference the truth
    contradicts is at 2.8, while six it agrees with lie between 4.1 and 5.9. The numbers,
    (specificity, overlap, SDlogJ), are the cases' own."""
    _, result = cheat_case
    base = result.scores["truth"]
    scores = {
        "demons_3mm": _registration(
            base, "demons_3mm", spec=demons[0], overlap=demons[1], sdlogj=demons[2]
        ),
        "bspline_40mm": _registration(
            base,
            "bspline_40mm",
            spec=bspline[0],
            overlap=bspline[1],
            sdlogj=bspline[2],
            family=("pairwise", "elastix"),
        ),
    }
    pair = [{"demons_3mm", "bspline_40mm"}]
    comparisons = []
    for measure, key in (("specificity", None), ("overlap.inverse_volume", "inverse_volume")):
        values = {
            k: (s.specificity.value if key is None else s.overlap[key]) for k, s in scores.items()
        }
        comparisons += _separable_where(values, pair, measure)
    v = verdict(scores, comparisons, has_labels=True)
    assert v.decisions == ()


@pytest.mark.xfail(
    strict=True,
    reason="FRESH19 (docs/verdict.md): the label overlap itself contradicts the truth here, "
    "beyond the rate roughness can buy within one family; not fixed",
)
def test_a_finer_grid_is_not_decided_better_by_an_overlap_the_truth_contradicts(cheat_case):
    """The benchmark's FRESH19, declared before it ran: on the phantom's FAMILIES_MIX case
    `families_phantom2d_mix_s91` the verdict with labels decides a 20 mm B-spline grid
    (SDlogJ 0.22, true error 2.01 mm) better than a 40 mm grid of the same engine (SDlogJ
    0.10, 1.66 mm) by the overlap's separable 1.67x odds: ln(odds ratio) / dr = 4.4, above
    OVERLAP_EXCHANGE_RATE (4.1, set on the tuning splits at 10% above their steepest wrong,
    3.72). Specificity prefers the 20 mm grid too (1.34x, bought by roughness). Open would
    be the right answer. The numbers, the subject-level intervals included, are the case's
    own; on both scans."""
    from itk_nrreval.measures.confidence import Comparison

    _, result = cheat_case
    base = result.scores["truth"]
    elastix = ("pairwise", "elastix")
    scores = {
        "bspline_20mm": _registration(
            base, "bspline_20mm", spec=11.156, overlap=0.7135, sdlogj=0.221, family=elastix
        ),
        "bspline_40mm": _registration(
            base, "bspline_40mm", spec=14.945, overlap=0.5987, sdlogj=0.104, family=elastix
        ),
    }
    a, b = "bspline_20mm", "bspline_40mm"
    comparisons = [
        Comparison("specificity", a, b, -3.790, (-5.275, -2.304), True),
        Comparison("overlap.inverse_volume", a, b, 0.1148, (0.0383, 0.1913), True),
    ]
    v = verdict(scores, comparisons, has_labels=True, dimension=2)
    assert v.decisions == ()


def test_demons_over_a_coarse_bspline_by_specificity_stays_open(cheat_case):
    """The benchmark's FRESH17, declared before it ran: on the phantom's FAMILIES_SYN case
    `families_phantom2d_syn_s76` the verdict without labels decided demons at 3 mm (SDlogJ
    0.18, true error 1.79 mm) better than a 40 mm B-spline (SDlogJ 0.12, 1.60 mm) by a
    separable 1.44x lower specificity, above the exp(5.5 x 0.061) = 1.40x its extra roughness
    could buy within one family: ln(ratio) / dr = 6.0. The same pair as FRESH13's and
    FRESH16's, decided there by the overlap; here the description length prefers demons too
    (z = 11). Open is the right answer: across families the rate is
    EXCHANGE_RATE_ACROSS_FAMILIES (6.6, fifteenth session). The numbers, specificity and
    SDlogJ, are the case's own."""
    _, result = cheat_case
    base = result.scores["truth"]
    scores = {
        "demons_3mm": _registration(base, "demons_3mm", spec=10.729, sdlogj=0.180),
        "bspline_40mm": _registration(
            base, "bspline_40mm", spec=15.455, sdlogj=0.119, family=("pairwise", "elastix")
        ),
    }
    v = _specificity_verdict(scores, {"demons_3mm", "bspline_40mm"}, dimension=2)
    assert v.decisions == ()


def test_a_coarser_grid_is_not_decided_better_by_smoother_fields_alone(cheat_case):
    """The benchmark's FRESH17, declared before it ran: on `families_mni2d_span_s79` the
    verdict decided a 60 mm B-spline grid (SDlogJ 0.11, true error 1.86 mm) better than a
    25 mm grid (SDlogJ 0.30, 1.34 mm) of the same engine, by the smoother-fields rule: the
    25 mm grid's specificity advantage (1.42x here, at most 1.52x in the case's interval) was
    below the exp(2.3 x 0.19) = 1.55x its extra roughness had to buy at the SMOOTHNESS_RATE
    of then. The overlap (discounted: rougher) and the description length (z = 2.3, below its
    3.2) both prefer the 25 mm grid, as the truth does. Open is the right answer: at today's
    rate (1.95, fifteenth session) the 25 mm grid's advantage reaches what it must buy. The
    numbers, the subject-level interval of the difference included, are the case's own."""
    from itk_nrreval.measures.confidence import Comparison

    _, result = cheat_case
    base = result.scores["truth"]
    elastix = ("pairwise", "elastix")
    scores = {
        "bspline_25mm": _registration(
            base, "bspline_25mm", spec=14.967, sdlogj=0.301, family=elastix
        ),
        "bspline_60mm": _registration(
            base, "bspline_60mm", spec=21.243, sdlogj=0.112, family=elastix
        ),
    }
    interval = Comparison(
        "specificity", "bspline_25mm", "bspline_60mm", -6.276, (-7.262, -5.290), True
    )
    v = verdict(scores, [interval], has_labels=False, dimension=2)
    assert v.decisions == ()
    assert "rougher" in v.open_pairs[0].reason


@pytest.mark.parametrize(
    ("other", "why"),
    [
        (("fluid", "simpleitk"), None),  # the rough one's own family
        (("pairwise", "elastix"), "are of different families"),
        (None, "are not known to be of one family"),  # no method and engine in the manifest
    ],
)
def test_across_families_roughness_must_buy_more_specificity(cheat_case, other, why):
    """A rougher registration's separable specificity advantage beyond exp(EXCHANGE_RATE dr)
    decides the pair within one family; across families or where a family is unknown
    (FRESH17: demons over a coarse B-spline, wrong at ln(ratio) / dr = 6.0) only beyond
    exp(EXCHANGE_RATE_ACROSS_FAMILIES dr), and the open pair says why. Checked just inside
    and just beyond each rate."""
    from itk_nrreval.measures.verdict import EXCHANGE_RATE, EXCHANGE_RATE_ACROSS_FAMILIES

    _, result = cheat_case
    base = result.scores["truth"]
    dr, smooth_spec = 0.1, 20.0
    same_family = why is None
    for rate, decided_within, decided_across in (
        (EXCHANGE_RATE * 0.98, False, False),
        ((EXCHANGE_RATE + EXCHANGE_RATE_ACROSS_FAMILIES) / 2, True, False),
        (EXCHANGE_RATE_ACROSS_FAMILIES * 1.02, True, True),
    ):
        scores = {
            "rough": _registration(
                base, "rough", spec=smooth_spec / np.exp(rate * dr), sdlogj=0.2 + dr
            ),
            "smooth": _registration(base, "smooth", spec=smooth_spec, sdlogj=0.2, family=other),
        }
        v = _specificity_verdict(scores, {"rough", "smooth"}, dimension=2)
        decided = decided_within if same_family else decided_across
        assert [(d.better, d.worse) for d in v.decisions] == (
            [("rough", "smooth")] if decided else []
        )
        if not decided and not same_family and rate > EXCHANGE_RATE:
            (pair,) = v.open_pairs
            assert why in pair.reason
            assert f"must reach {np.exp(EXCHANGE_RATE_ACROSS_FAMILIES * dr):.2f}x" in pair.reason


def test_the_description_length_decides_only_between_settings_of_one_family(cheat_case):
    """Issue 41: the description length's preference by at least MIN_Z jackknife standard
    errors is evidence between registrations of one family (method and engine), and none
    between families (the benchmark found it wrong there, in both directions); specificity's
    evidence the other way leaves the pair open."""
    from itk_nrreval.measures.description_length import MIN_Z, DescriptionLength

    _, result = cheat_case
    base = result.scores["truth"]
    spread = np.array([0.0, 1.0, -1.0, 2.0, -2.0, 0.5])  # jackknife deviations, shared

    def dl(bits, own):
        """`bits` with the jackknife's shared spread plus `own` (its own deviations)."""
        return DescriptionLength(bits, bits, 0.0, tuple(bits + spread + own), 1.0, 0.1)

    # z of a against b: the paired jackknife's standard error of `own`'s difference
    own = np.array([0.0, 1.0, -1.0, 1.0, -1.0, 0.0])
    stderr = np.sqrt(5 / 6 * np.sum((own - own.mean()) ** 2))

    def decided(gap, family_a, family_b, spec_a=10.0, spec_b=10.0, separable=False):
        # equal roughness; specificity separable only where asked
        a = dataclasses.replace(
            _registration(base, "a", spec=spec_a, sdlogj=0.2),
            description_length=dl(1000.0, own),
            family=family_a,
        )
        b = dataclasses.replace(
            _registration(base, "b", spec=spec_b, sdlogj=0.2),
            description_length=dl(1000.0 + gap, 0.0 * own),
            family=family_b,
        )
        values = {"a": spec_a, "b": spec_b}
        comparisons = _separable_where(values, [{"a", "b"}] if separable else [])
        v = verdict({"a": a, "b": b}, comparisons, has_labels=False)
        return [(d.better, d.worse, d.basis) for d in v.decisions]

    fluid = ("fluid", "simpleitk")
    above, below = 1.05 * MIN_Z * stderr, 0.95 * MIN_Z * stderr
    ((better, worse, basis),) = decided(above, fluid, fluid)
    assert (better, worse) == ("a", "b") and basis.startswith("description length")
    assert f"{MIN_Z * 1.05:.1f} standard errors" in basis
    assert decided(-above, fluid, fluid)[0][:2] == ("b", "a")
    assert decided(below, fluid, fluid) == []  # not enough standard errors
    assert decided(above, fluid, ("pairwise", "elastix")) == []  # another family
    assert decided(above, None, None) == []  # families unknown
    # specificity's evidence for b (1.3x at equal roughness) against it: open
    assert decided(above, fluid, fluid, spec_a=13.0, spec_b=10.0, separable=True) == []
    # and for a: both decide it
    ((_, _, basis),) = decided(above, fluid, fluid, spec_a=10.0, spec_b=13.0, separable=True)
    assert basis.startswith("specificity and description length")


@pytest.mark.parametrize(
    "family_syn, family_demons, decided",
    [
        (("fluid", "ants"), ("fluid", "simpleitk"), False),  # FRESH11's pair: two families
        (None, ("fluid", "simpleitk"), False),  # a family unknown
        (("fluid", "simpleitk"), ("fluid", "simpleitk"), True),  # settings of one family
    ],
)
def test_smoother_fields_decide_only_within_one_family(
    cheat_case, family_syn, family_demons, decided
):
    """FRESH11's wrong pair (docs/verdict.md): on the second scan of
    `families_mni2d_syn_s44` the verdict decided SyN (SDlogJ 0.20) better than 3 mm demons
    (SDlogJ 0.30) that corresponded better (1.44 against 1.67 mm), because the demons'
    specificity advantage (1.04x here) is less than the exp(SMOOTHNESS_RATE x 0.09) = 1.23x
    its extra roughness must buy. Between registrations of different families an SDlogJ
    difference says how each family regularises, not which one corresponds better: the pair
    stays open, and its reason says which way the rule leans and why it does not decide.
    The same numbers between two settings of one family decide, as before."""
    _, result = cheat_case
    base = result.scores["truth"]
    scores = {
        "syn": dataclasses.replace(
            _registration(base, "syn", spec=15.53, sdlogj=0.201), family=family_syn
        ),
        "demons_3mm": dataclasses.replace(
            _registration(base, "demons_3mm", spec=14.96, sdlogj=0.295), family=family_demons
        ),
    }
    v = _specificity_verdict(scores, {"syn", "demons_3mm"})
    if decided:
        assert [(d.better, d.worse) for d in v.decisions] == [("syn", "demons_3mm")]
        assert "that much roughness must buy" in v.decisions[0].basis
        return
    assert v.decisions == ()
    ((pair),) = v.open_pairs
    assert pair.leans_to == "syn"  # the hint, structured: results.json 'open'
    assert pair.to_dict()["leans_to"] == "syn"
    assert "1 of them leans one way" in " ".join(v.text)
    assert "Leaning, not decided: syn over demons_3mm." in v.text  # named, for the report
    assert "so it leans to syn" in pair.reason
    why = "are of different families" if family_syn else "the family of syn is unknown"
    assert why in pair.reason


@pytest.mark.parametrize(
    "sdlogj_rough, decided",
    [
        (0.295, False),  # FRESH11's and FRESH19's pair: 0.09 rougher, the rougher was better
        (0.368, False),  # 0.17 rougher, as FRESH13's demons at 3 mm over a 15 mm grid
        (0.411, True),  # 0.21 rougher: just above ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE
        (0.75, True),  # the median difference of the benchmark's right leans is 0.55
    ],
)
@pytest.mark.parametrize("family_rough", [("pairwise", "elastix"), None])
def test_smoother_fields_decide_across_families_only_by_a_large_difference(
    cheat_case, sdlogj_rough, decided, family_rough
):
    """Between registrations of different (or unknown) families, the smoother-fields rule
    decides only where the rougher one's SDlogJ is higher by at least
    ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE; below it, it leans. The wrong leans of the
    benchmark's splits had differences of 0.09 and 0.17 (docs/verdict.md). The specificities
    are FRESH11's: the rougher one's advantage (1.04x) buys too little at any of these."""
    from itk_nrreval.measures.verdict import ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE

    _, result = cheat_case
    base = result.scores["truth"]
    smooth = _registration(base, "smooth", spec=15.53, sdlogj=0.201)
    rough = _registration(base, "rough", spec=14.96, sdlogj=sdlogj_rough)
    scores = {
        "smooth": dataclasses.replace(smooth, family=("fluid", "ants")),
        "rough": dataclasses.replace(rough, family=family_rough),
    }
    difference = sdlogj_rough - 0.201
    assert (difference >= ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE) == decided
    v = _specificity_verdict(scores, {"smooth", "rough"})
    if decided:
        assert [(d.better, d.worse) for d in v.decisions] == [("smooth", "rough")]
        basis = v.decisions[0].basis
        assert "that much roughness must buy" in basis
        assert "across families (smooth: fluid/ants and rough: " in basis
        assert f"least the {ACROSS_FAMILIES_ROUGHNESS_DIFFERENCE:g} in SDlogJ that decides" in basis
        assert v.open_pairs == ()
        # not where the rougher one folds: issue 41's own case had a 25 mm B-spline folding
        # 2.3% (SDlogJ 0.54) correspond better than demons at 1 mm (0.29)
        folds = dataclasses.replace(
            _registration(base, "rough", spec=14.96, sdlogj=sdlogj_rough, folded=0.023),
            family=family_rough,
        )
        v = _specificity_verdict({**scores, "rough": folds}, {"smooth", "rough"})
        assert v.decisions == ()
        assert v.open_pairs[0].leans_to == "smooth"
        return
    assert v.decisions == ()
    ((pair),) = v.open_pairs
    assert pair.leans_to == "smooth"
    assert "so it leans to smooth" in pair.reason


def test_the_leaning_sentence_names_six_pairs_then_counts_the_rest():
    """The verdict's text names the open pairs that lean (the registration leaned to first),
    at most six; the others are counted (all are in results.json 'open')."""
    from itk_nrreval.measures.verdict import OpenPair, _leaning_sentence

    pairs = [OpenPair(f"a{i}", f"b{i}", "why", f"b{i}" if i % 2 else f"a{i}") for i in range(8)]
    sentence = _leaning_sentence(pairs)
    assert sentence == (
        "Leaning, not decided: a0 over b0; b1 over a1; a2 over b2; b3 over a3; a4 over b4; "
        "b5 over a5; and 2 more."
    )
    assert _leaning_sentence(pairs[:1]) == "Leaning, not decided: a0 over b0."
