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
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_evaluate import N_IMAGES, make_case

import itk_nrreval as nr
from data_synth.cheat import class_matching_cheat
from itk_nrreval.cli import main
from itk_nrreval.confidence import compare
from itk_nrreval.evaluation import verdict

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


def test_cheat_is_flagged_and_ranked_after_every_genuine_registration(cheat_case):
    _, result = cheat_case
    cheat = result.scores["cheat"]
    assert cheat.flags and "fold" in cheat.flags[0]
    assert cheat.plausibility.folded_fraction > 1e-3
    assert cheat.plausibility.jacobian_min <= 0  # never clipped
    assert result.verdict.ranking[-1] == "cheat"
    assert "cheat" not in result.verdict.best
    assert not result.scores["truth"].flags and not result.scores["perturbed"].flags
    assert result.verdict.ranking[:2] == ("truth", "perturbed")
    assert any(t.startswith("cheat is flagged: ") for t in result.verdict.text)


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
    assert res["verdict"]["ranking"][-1] == "cheat"
    assert res["verdict"]["best"][0] == "truth" and res["verdict"]["text"]
    decided = {(d["better"], d["worse"]): d["basis"] for d in res["verdict"]["decisions"]}
    for name in ("truth", "perturbed", "identity"):  # the cheat folds: it is flagged
        assert decided[(name, "cheat")].startswith("flag: ") and "fold" in decided[(name, "cheat")]
    assert decided[("truth", "identity")] == "specificity (subject-level interval separable)"
    summary = (out / "summary.md").read_text()
    assert summary.startswith(res["verdict"]["text"][0])
    assert "95% CI" in summary and "cheat is flagged" in summary
    json.dumps(res, allow_nan=False)  # valid JSON: no NaN anywhere


def test_confidence_off_gives_no_intervals(tmp_path):
    make_case(tmp_path)
    result = nr.evaluate(tmp_path / "manifest.yaml", confidence=False, **KW)
    assert result.comparisons == () and result.scores["truth"].intervals == {}
    assert result.verdict.best == ("truth",)
    assert "not computed" in result.verdict.text[0]
    assert result.verdict.decisions == ()  # nothing flagged, nothing separable: all open
    with pytest.raises(ValueError, match="confidence_samples: expected an integer >= 2"):
        nr.evaluate(tmp_path / "manifest.yaml", confidence_samples=1, **KW)


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


SEPARABLE = "specificity (subject-level interval separable)"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 6),
    noise=st.sampled_from([0.01, 0.3, 3.0]),
    p_flag=st.sampled_from([0.0, 0.3, 1.0]),
    confidence=st.booleans(),
)
def test_decisions_agree_with_ranking_and_comparisons(
    cheat_case, seed, n, noise, p_flag, confidence
):
    """Each decision follows the ranking; a pair is decided exactly when its registrations
    differ in being flagged (the unflagged one wins) or, flagged alike, their specificity
    difference is separable (the lower one wins); every other pair is open."""
    _, result = cheat_case
    base = result.scores["truth"]
    rng = np.random.default_rng(seed)
    names = [f"r{i}" for i in range(n)]
    values = dict(zip(names, np.round(rng.uniform(1, 3, n), 1), strict=True))  # some ties
    n_groups = 6
    replicates = {k: v + noise * rng.standard_normal(n_groups) for k, v in values.items()}
    flagged = {k for k in names if rng.random() < p_flag}
    scores = {
        k: dataclasses.replace(
            base,
            name=k,
            specificity=dataclasses.replace(base.specificity, value=float(values[k])),
            flags=("0.2% of voxels fold (test)",) if k in flagged else (),
        )
        for k in names
    }
    comparisons = compare("specificity", values, replicates) if confidence else []
    separable = {frozenset((c.a, c.b)) for c in comparisons if c.separable}
    v = verdict(scores, comparisons, has_labels=False)

    pairs = [frozenset((d.better, d.worse)) for d in v.decisions]
    assert len(pairs) == len(set(pairs))  # no pair decided twice, so never both ways
    expected = {
        frozenset((a, b))
        for a, b in itertools.combinations(names, 2)
        if (a in flagged) != (b in flagged) or frozenset((a, b)) in separable
    }
    assert set(pairs) == expected  # the rest are open
    for d in v.decisions:
        assert v.ranking.index(d.better) < v.ranking.index(d.worse)
        if (d.better in flagged) != (d.worse in flagged):
            assert d.worse in flagged and d.basis == "flag: 0.2% of voxels fold (test)"
        else:
            assert d.basis == SEPARABLE and values[d.better] < values[d.worse]
        assert d.worse != v.best[0]
        assert d.to_dict() == {"better": d.better, "worse": d.worse, "basis": d.basis}
    if confidence:  # whatever is not among the best is decided worse than the top one
        pool = [k for k in v.ranking if k not in flagged] or v.ranking
        decided = {(d.better, d.worse) for d in v.decisions}
        assert all((v.best[0], k) in decided for k in pool if k not in v.best)
    assert v.to_dict()["decisions"] == [d.to_dict() for d in v.decisions]
