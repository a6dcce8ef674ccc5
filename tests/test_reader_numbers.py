"""Numbers a reader sees: relative ranks within noise, interval supports, frame-spread words,
numbers formatted for people, and the CLI's help and minimums."""

from __future__ import annotations

import math

import SimpleITK as sitk
import yaml
from hypothesis import given
from hypothesis import strategies as st
from test_evaluate import make_case

import itk_nrreval as nr
from itk_nrreval.evaluation import TIE_Z, tie_groups
from itk_nrreval.reports import results_csv, summary_table

# ----------------------------------------------------------------------------- relative ranks


def twice_the_same_registration(tmp_path) -> dict:
    """The true registration, and the same transforms again behind a 1e-4 mm translation.

    The two differ by far less than the Monte-Carlo error of their specificity (like the same
    transforms read through SimpleITK and through ITK), so no reader should be told one is
    at 100% and the other at 0%.
    """
    data = make_case(tmp_path, with_labels=False)
    sitk.WriteTransform(sitk.TranslationTransform(2, (1e-4, 0.0)), str(tmp_path / "tiny.tfm"))
    truth = data["registrations"]["truth"]
    again = {
        "reference": truth["reference"],
        "transforms": [["tiny.tfm", t] for t in truth["transforms"]],
    }
    data["registrations"] = {"truth": truth, "truth_again": again}
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return data


def test_the_same_transforms_given_twice_are_tied_not_0_and_100(tmp_path):
    twice_the_same_registration(tmp_path)
    res = nr.evaluate(tmp_path / "manifest.yaml", n_samples=500, progress=False)
    spec = {n: s.specificity for n, s in res.scores.items()}
    gap = abs(spec["truth"].value - spec["truth_again"].value)
    assert 0 < gap < spec["truth"].stderr  # a difference inside the noise, not none
    for measure in res.measures:
        assert res.relative_ranks[measure] == {"truth": 100.0, "truth_again": 100.0}, measure
        assert res.ranks[measure] == {"truth": 1, "truth_again": 1}, measure
        assert res.tied_with(measure, "truth") == ("truth_again",)
    assert "| 1 (tied) | 100.0% |" in summary_table(res)
    assert res.to_dict()["registrations"]["truth"]["tied_with"]["specificity"] == ["truth_again"]
    assert ",truth_again,truth_again," in results_csv(res).splitlines()[1]


scores_st = st.dictionaries(
    st.sampled_from("abcdefg"),
    st.tuples(st.floats(0.0, 10.0, allow_nan=False), st.floats(0.0, 0.5, allow_nan=False)),
    min_size=1,
)


@given(scores_st, st.booleans())
def test_relative_ranks_never_split_scores_within_their_errors(data, hib):
    scores = {k: v for k, (v, _) in data.items()}
    stderr = {k: se for k, (_, se) in data.items()}
    kw = dict(higher_is_better=hib, stderr=stderr)
    rel = nr.relative_ranks(scores, **kw)
    rank = nr.ranks(scores, **kw)
    for a in scores:
        for b in scores:
            # an independent reference: a pair inside its combined 95% noise band
            if abs(scores[a] - scores[b]) <= TIE_Z * math.hypot(stderr[a], stderr[b]):
                assert rel[a] == rel[b] and rank[a] == rank[b]
            # order is kept: a better score never gets a lower relative rank
            if (scores[a] > scores[b]) == hib and scores[a] != scores[b]:
                assert rel[a] >= rel[b] and rank[a] <= rank[b]
    groups = tie_groups(scores, **kw)
    assert sorted(k for g in groups for k in g) == sorted(scores)
    assert {rel[g[0]] for g in groups[:1]} == {100.0}
    if len(groups) > 1:
        assert {rel[k] for k in groups[-1]} == {0.0}


def test_a_tie_between_non_neighbours_takes_in_the_scores_between():
    # a and b are within their noise; c, between them, is within b's but not a's
    scores = {"a": 0.0, "c": 0.2, "b": 0.25}
    stderr = {"a": 0.1, "c": 0.0, "b": 0.1}
    assert tie_groups(scores, higher_is_better=False, stderr=stderr) == [("a", "c", "b")]
    rel = nr.relative_ranks({**scores, "d": 9.0}, higher_is_better=False, stderr=stderr)
    assert rel == {"a": 100.0, "c": 100.0, "b": 100.0, "d": 0.0}
