"""Rank stability people can see (issue 45, item 2): every registration's rank over
bootstraps of the subjects' jackknife contributions, and which registration is told apart
from which. A clear order keeps all its mass on one rank per registration; two registrations
of equal quality split theirs; the significance map says what the comparisons say."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from test_evaluate import make_case

import itk_nrreval as nr
from itk_nrreval.measures.confidence import bootstrap_ranks, significance_map


@pytest.fixture(scope="module")
def clear_order(tmp_path_factory):
    """The generated 2D case of test_evaluate: the true registration, a perturbed one and
    the identity, in that order by every measure (separably, 6 subjects), evaluated with
    subject-level confidence and its report."""
    folder = tmp_path_factory.mktemp("clear")
    make_case(folder)
    out = folder / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nr.evaluate(
            folder / "manifest.yaml",
            n_samples=1000,
            inverse_consistency=False,
            progress=False,
        )
    result.write(out)
    return result, out


def test_a_clear_order_has_all_its_mass_on_one_rank(clear_order):
    result, out = clear_order
    measures = ["specificity", "generalization", *(m for m in result.measures if "overlap" in m)]
    assert set(result.rank_stability) == set(measures)
    saved = json.loads((out / "results.json").read_text())["rank_stability"]
    for measure in measures:
        rs = result.rank_stability[measure]
        assert rs.n_bootstrap == 200 and rs.seed == result.options["seed"]
        if measure != "generalization":  # its order is not the point here
            expected = {"truth": 1, "perturbed": 2, "identity": 3}
            assert {n: result.ranks[measure][n] for n in expected} == expected, measure
            for name, rank in expected.items():
                row = rs.frequencies[rs.names.index(name)]
                assert row[rank - 1] == 1.0 and row.sum() == 1.0, (measure, name)
                assert rs.median_rank(name) == rank == rs.ranks[rs.names.index(name)]
        got = saved[measure]["frequencies"]
        assert got == {n: rs.frequencies[i].tolist() for i, n in enumerate(rs.names)}


def test_the_significance_map_says_what_the_comparisons_say(clear_order):
    result, out = clear_order
    saved = json.loads((out / "results.json").read_text())
    sig = saved["significance"]
    for c in saved["comparisons"]:
        up = c["measure"].startswith("overlap")
        if not c["separable"]:
            assert sig[c["measure"]][c["a"]][c["b"]] == "not separable"
            continue
        a_better = (c["difference"] > 0) == up  # the a - b difference, read by hand
        assert sig[c["measure"]][c["a"]][c["b"]] == ("better" if a_better else "worse")
        assert sig[c["measure"]][c["b"]][c["a"]] == ("worse" if a_better else "better")
    decided = {(d["better"], d["worse"]) for d in saved["verdict"]["decisions"]}
    for a, row in sig["verdict"].items():
        for b, cell in row.items():
            want = "decided better" if (a, b) in decided else None
            want = want or ("decided worse" if (b, a) in decided else "open")
            assert cell == want
    assert sig["specificity"]["truth"]["identity"] == "better"
    # both figures are files and are embedded in the report, with their captions
    page = (out / "report.html").read_text()
    for name in ("rank_stability.png", "significance.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG"
        assert f'alt="{name}"' in page
    assert "challengeR's blob plot" in page and "Which registration is told apart" in page


def test_two_registrations_of_equal_quality_split_their_mass():
    """B's subjects contribute what A's do, subjects swapped in pairs: the same quality, so
    every draw of the subjects has its mirror draw in which the two trade places; each is
    best in about half of the draws. A third, clearly worse one stays last."""
    rng = np.random.default_rng(11)
    g = 16
    reps_a = 0.70 + 0.005 * rng.standard_normal(g)
    swap = np.arange(g).reshape(-1, 2)[:, ::-1].reshape(-1)  # 1, 0, 3, 2, ...
    reps = {"a": reps_a, "b": reps_a[swap], "worse": reps_a - 0.2}
    values = {"a": 0.70, "b": 0.70, "worse": 0.50}
    rs = bootstrap_ranks("overlap.volume", values, reps, higher_is_better=True, seed=3)
    first = rs.frequencies[:, 0]
    assert 0.35 < first[0] < 0.65 and 0.35 < first[1] < 0.65
    assert first[0] + first[1] == pytest.approx(1.0)  # no draw ties them
    np.testing.assert_array_equal(rs.frequencies[2], [0.0, 0.0, 1.0])
    assert rs.ranks == (1, 1, 3)  # on all subjects: a and b equal
    # registrations equal in every subject are tied in every draw: both take rank 1
    tied = bootstrap_ranks(
        "specificity",
        {"a": 0.3, "same": 0.3},
        {"a": reps_a, "same": reps_a.copy()},
        higher_is_better=False,
    )
    np.testing.assert_array_equal(tied.frequencies, [[1.0, 0.0], [1.0, 0.0]])


def test_bootstrap_draws_are_seeded_and_paired():
    """The same seed gives the same shares; the draws are shared by the registrations, so a
    registration that is another plus a constant is always behind it."""
    rng = np.random.default_rng(5)
    base = rng.normal(0.2, 0.05, 10)
    values = {"x": 0.2, "y": 0.2001}
    reps = {"x": base, "y": base + 0.0001}  # a hair worse in every subject
    one = bootstrap_ranks("specificity", values, reps, higher_is_better=False, seed=9)
    two = bootstrap_ranks("specificity", values, reps, higher_is_better=False, seed=9)
    np.testing.assert_array_equal(one.frequencies, two.frequencies)
    np.testing.assert_array_equal(one.frequencies, [[1.0, 0.0], [0.0, 1.0]])
    nan = bootstrap_ranks("specificity", {"x": 0.2, "y": np.nan}, reps, higher_is_better=False)
    assert np.isnan(nan.frequencies).all()
    assert significance_map([], "specificity", ["x", "y"]) == {
        "x": {"y": "not compared"},
        "y": {"x": "not compared"},
    }
