"""Numbers a reader sees: relative ranks within noise, interval supports, frame-spread words,
numbers formatted for people, and the CLI's help and minimums."""

from __future__ import annotations

import argparse
import math
import re

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from test_evaluate import make_case

import itk_nrreval as nr
from itk_nrreval.evaluation import TIE_Z, tie_groups
from itk_nrreval.measures.confidence import jackknife_interval, measure_bounds
from itk_nrreval.report.evaluation_page import report_html
from itk_nrreval.report.evaluation_text import results_csv, summary_table

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


# ----------------------------------------------------------------------------- intervals


def leave_one_out_means(x: np.ndarray) -> np.ndarray:
    return (x.sum() - x) / (x.size - 1)


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.float64, st.integers(4, 30), elements=st.floats(0.0, 100.0)))
def test_an_interval_of_a_quantity_that_cannot_be_negative_never_goes_below_0(x):
    """The mean of nonnegative values (a distance, like generalization), jackknifed."""
    iv = jackknife_interval(x.mean(), leave_one_out_means(x), bounds=(0.0, math.inf))
    assert iv.lo >= 0.0 and iv.lo <= x.mean() <= iv.hi


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.float64, st.integers(4, 30), elements=st.floats(0.0, 1.0)))
def test_an_interval_of_an_overlap_stays_in_0_to_1(x):
    iv = jackknife_interval(x.mean(), leave_one_out_means(x), bounds=(0.0, 1.0))
    assert 0.0 <= iv.lo <= x.mean() <= iv.hi <= 1.0


def test_the_reported_example_of_a_negative_lower_end_is_gone():
    # generalization-like: a few images far from the model, most near it (skewed, N = 6)
    x = np.array([0.02, 0.03, 0.05, 0.04, 0.03, 6.0])
    linear = jackknife_interval(x.mean(), leave_one_out_means(x))
    assert linear.lo < 0  # what the reader was shown
    iv = jackknife_interval(
        x.mean(), leave_one_out_means(x), bounds=measure_bounds("generalization")
    )
    assert 0 < iv.lo < x.mean() < iv.hi and iv.stderr == linear.stderr


def test_interval_on_the_log_scale_covers_as_the_linear_one_on_well_behaved_data():
    """Coverage of the true mean of a gamma(shape 8) population, N = 20, 400 draws."""
    rng = np.random.default_rng(7)
    covered = {"linear": 0, "log": 0}
    for _ in range(400):
        x = rng.gamma(8.0, 1.0, size=20)  # true mean 8
        reps = leave_one_out_means(x)
        for kind, bounds in (("linear", (-math.inf, math.inf)), ("log", (0.0, math.inf))):
            iv = jackknife_interval(x.mean(), reps, bounds=bounds)
            covered[kind] += iv.lo <= 8.0 <= iv.hi
    assert abs(covered["log"] - covered["linear"]) <= 8  # within 2% of each other
    assert 0.92 * 400 <= covered["log"] <= 0.98 * 400
    # and with a small relative spread the two intervals nearly coincide
    x = rng.normal(100.0, 1.0, size=30)
    a = jackknife_interval(x.mean(), leave_one_out_means(x))
    b = jackknife_interval(x.mean(), leave_one_out_means(x), bounds=(0.0, math.inf))
    assert b.lo == pytest.approx(a.lo, rel=1e-4) and b.hi == pytest.approx(a.hi, rel=1e-4)


# ----------------------------------------------------------------------------- one small run

#: The flag threshold for the run below: 2.5% of its 40 mm field of view, 1 mm. Its identity
#: registration's frame estimates spread 1.5 mm on average (flagged), perturbed's 0.64 mm
#: (not flagged) though perturbed's largest single spread is 2.1 mm.
FRAME_FRACTION = 0.025


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("reader")
    make_case(tmp)
    thresholds = nr.Thresholds(frame_spread_fraction=FRAME_FRACTION)
    with pytest.warns(RuntimeWarning, match="flagged"):
        result = nr.evaluate(
            tmp / "manifest.yaml", n_samples=300, progress=False, thresholds=thresholds
        )
    return result, summary_table(result), report_html(result, figures={})


def _row(html: str, section: str, name: str) -> list[str]:
    """The cells' text of the first row whose first cell is `name` in the page's `section`."""
    body = html.split(f'<section id="{section}"', 1)[1].split("</section>", 1)[0]
    for row in re.findall(r"<tr[^>]*>(.*?)</tr>", body):
        cells = [re.sub("<[^>]+>", "", c) for c in re.findall(r"<t[dh][^>]*>(.*?)</t[dh]>", row)]
        if cells and cells[0] == name:
            return cells
    raise AssertionError(f"no row of {name} in {section}")


def test_the_frame_spread_the_report_calls_doubtful_is_the_one_flagged(run):
    result, summary, html = run
    limit = FRAME_FRACTION * 40.0  # the 40 x 40 grid of 1 mm voxels: an independent number
    spreads = {n: s.frame.spread_mean_mm for n, s in result.scores.items()}
    assert spreads["perturbed"] < limit < spreads["identity"]
    assert result.scores["perturbed"].frame.spread_max_mm > limit  # max is not judged
    for text in (summary, html):
        assert f"above {limit:g} mm (2.5% of the 40 mm field of view" in text
        assert "doubtful" in text and "max spread" in text and "not judged" in text
    for name, s in result.scores.items():
        flagged = any("frame estimates spread" in f for f in s.flags)
        assert flagged == (spreads[name] > limit), name
        assert _row(html, "frames", name)[3] == ("flagged" if flagged else "no"), name
        assert f"| {name} | {s.frame.method} | " in summary
        cell = summary.split(f"| {name} | {s.frame.method} | ", 1)[1].split(" | ")[1]
        assert cell == ("yes" if flagged else "no"), name


# ----------------------------------------------------------------------------- for people

PYTHON_INTERNALS = re.compile(r"np\.(?:float|int|uint|bool)\w*\(|array\(|dtype|\bNone\b")


def test_reports_show_no_python_internals(run):
    result, summary, html = run
    assert not PYTHON_INTERNALS.findall(summary)
    page_text = re.sub("<[^>]+>", " ", html.split("<body", 1)[1])  # what a reader sees
    assert not PYTHON_INTERNALS.findall(page_text), set(PYTHON_INTERNALS.findall(page_text))
    # the identity registration's reference index is shown; the others have none
    assert _row(html, "inputs", "identity")[2] == "0"
    assert _row(html, "inputs", "truth")[2] == "–"


@pytest.mark.parametrize(
    "call",
    [
        lambda: nr.evaluate({}, n_samples=np.int64(1)),
        lambda: nr.evaluate({}, confidence=nr.Confidence(samples=np.int64(1))),
        lambda: nr.evaluate(
            {},
            resampling=nr.Resampling(
                label_interpolation="gaussian", label_sigma_mm=np.float64(-62)
            ),
        ),
        lambda: nr.overlap_table(np.ones((3, 4, 4), int), spacing=(np.float64(-1.0), 1.0)),
        lambda: nr.overlap_table(np.ones((3, 4, 4), int), label_values=np.array([1, 1])),
        lambda: nr.overlap_table(np.ones((3, 4, 4), int), label_values=np.array([1.0, 2.5])),
        lambda: nr.overlap_table([sitk.GetImageFromArray(np.full((4, 4), 0.3, np.float32))] * 3),
    ],
)
def test_messages_show_numbers_as_people_write_them(call):
    with pytest.raises(ValueError) as info:
        call()
    assert not PYTHON_INTERNALS.findall(str(info.value)), str(info.value)


# ----------------------------------------------------------------------------- the CLI


def _options_with_defaults():
    """(command, option, default, help expanded as argparse prints it) of every option that
    takes a value and has a default."""
    from itk_nrreval.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for command, sub in commands.choices.items():
        for action in sub._actions:
            if not action.option_strings or action.nargs == 0:  # positional, or a switch
                continue
            if action.default is None or action.default is argparse.SUPPRESS:
                continue
            yield (
                command,
                action.option_strings[0],
                action.default,
                sub._get_formatter()._expand_help(action) if action.help else "",
            )


def test_every_option_with_a_default_says_it_in_its_help():
    missing = []
    for command, option, default, text in _options_with_defaults():
        if isinstance(default, (list, tuple)):
            shown = [",".join(f"{v:g}" for v in default)]
        elif isinstance(default, float):
            shown = [f"{default:g}"]
        elif isinstance(default, int):
            shown = [str(default), f"{default:,}"]
        else:
            shown = [str(default)]
        if "default" not in text or not any(s in text for s in shown):
            missing.append(f"{command} {option} (default {default}): {text!r}")
    assert not missing, "\n".join(missing)


@pytest.mark.parametrize("n", ["0", "1", "2"])
def test_synth_refuses_fewer_images_than_evaluate_needs(tmp_path, capsys, n):
    from itk_nrreval.cli import main

    assert main(["synth", "--n", n, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--n" in err and ">= 3" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
