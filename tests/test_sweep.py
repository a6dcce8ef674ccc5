"""Parameter sweeps: one registration per setting, cached, checked before any work."""

from __future__ import annotations

import json

import pytest
import yaml
from test_bad_inputs import assert_one_line

import itk_nrreval as nr
from itk_nrreval.cli import main
from itk_nrreval.experiments.sweep import parse_parameter


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sweep") / "data"
    assert main(["synth", "--n", "5", "--out", str(folder), "--seed", "2"]) == 0
    return folder / "manifest.yaml"


def sweep_args(population, out, values: str) -> list[str]:
    return [
        "sweep",
        "--from",
        str(population),
        "--truth",
        "truth",
        "--method",
        "fluid",
        "--param",
        f"smoothing_mm={values}",
        "--param",
        "iterations=20:10:5",
        "--out",
        str(out),
        "--samples",
        "1000",
        "--quiet",
    ]


def test_sweep_writes_one_registration_per_setting_and_reuses_them(population, tmp_path, capsys):
    out = tmp_path / "sweep"
    assert main(sweep_args(population, out, "2,6")) == 0
    first = json.loads((out / "sweep.json").read_text())
    names = [row["registration"] for row in first["settings"]]
    assert names == [
        "fluid_smoothing_mm-2_iterations-20:10:5",
        "fluid_smoothing_mm-6_iterations-20:10:5",
    ]
    assert [row["smoothing_mm"] for row in first["settings"]] == [2.0, 6.0]
    manifest = yaml.safe_load((out / "manifest.yaml").read_text())
    assert list(manifest["registrations"]) == names
    recorded = [r["parameters"] for r in manifest["registrations"].values()]
    family = {"method": "fluid", "engine": "simpleitk"}
    assert recorded == [
        {**family, "smoothing_mm": 2.0, "iterations": [20, 10, 5]},
        {**family, "smoothing_mm": 6.0, "iterations": [20, 10, 5]},
    ]
    assert manifest["labels"] and manifest["images"]
    # every setting is scored, with the truth beside it, and the figure is written
    for row in first["settings"]:
        assert row["specificity"] > 0 and 0 < row["overlap.inverse_volume"] <= 1
        assert row["true_correspondence_error_mm"] > 0
    assert set(first["not_separable"]) <= set(names)
    assert (out / "sweep.png").stat().st_size > 0
    _check_report(out, first)
    logs = {n: (out / "registrations" / n / "registration.json").stat().st_mtime_ns for n in names}

    # one more value: the two earlier registrations are reused, not run again
    capsys.readouterr()
    assert main(sweep_args(population, out, "2,6,12")) == 0
    second = json.loads((out / "sweep.json").read_text())
    assert [row["reused"] for row in second["settings"]] == [True, True, False]
    for n, mtime in logs.items():
        assert (out / "registrations" / n / "registration.json").stat().st_mtime_ns == mtime
    assert "3 settings (2 already registered)" in capsys.readouterr().out
    # Earlier settings' scores may move with the new one: the scores are taken where every
    # image covers the grid under every registration compared. The same sweep again gives
    # the same numbers, from the registrations and the evaluation's cache alone.
    assert main(sweep_args(population, out, "2,6,12")) == 0
    third = json.loads((out / "sweep.json").read_text())
    assert all(row["reused"] for row in third["settings"])
    assert third["settings"] == [dict(row, reused=True) for row in second["settings"]]
    results = json.loads((out / "evaluation" / "results.json").read_text())
    run = results["run"]
    # only the images are resampled again: they leave the cache once scored (issue 30)
    resampled = len(results["registrations"]) * len(results["inputs"]["images"])
    assert run["cache_computed"] == resampled and run["cache_reused"] > 0


def _check_report(out, summary: dict) -> None:
    """The sweep's page: self-contained, the verdict (with the truth's choice) before the
    table, every setting a row, its figure and the evaluation's mean images embedded as the
    files written beside it; the evaluation's own page written too."""
    from test_html_report import check_self_contained, decode_png, parse

    page, raw = parse(out / "report.html")
    check_self_contained(page, raw)
    text = " ".join(" ".join(page.text).split())
    assert "<script" not in raw.lower()
    _check_recommendation(out, summary, raw)
    rec = summary["recommended"]
    head = "The verdict recommends" if rec is not None else "No setting is recommended"
    verdict = text.index(head)
    named = rec if rec is not None else summary["not_separable"][0]
    assert text.index(named, verdict) < text.index("Every setting", verdict)
    assert "The truth's choice" in text
    truth_best = summary["best_by"]["true_correspondence_error_mm"]
    assert truth_best in text[verdict : text.index("Every setting", verdict)]
    for row in summary["settings"]:
        assert row["registration"] in text
        assert "setting-" + row["registration"].replace(":", "-") in page.ids
    embedded = {decode_png(src) for src in page.srcs}
    assert (out / "sweep.png").read_bytes() in embedded
    assert (out / "evaluation" / "mean_images.png").read_bytes() in embedded
    assert len(page.srcs) == 2
    inner, inner_raw = parse(out / "evaluation" / "report.html")
    check_self_contained(inner, inner_raw)
    assert not list(out.glob(".*tmp*"))  # no temporary left behind


def _check_recommendation(out, summary: dict, raw: str) -> None:
    """A setting is recommended (sweep.json, the star in the page's table) exactly when the
    evaluation's verdict (its results.json) decides it better than every other setting,
    one by one, and it is not flagged; never otherwise (issue 26, issue 44)."""
    import re

    results = json.loads((out / "evaluation" / "results.json").read_text())
    decided = {(d["better"], d["worse"]) for d in results["verdict"]["decisions"]}
    names = [row["registration"] for row in summary["settings"]]
    flagged = {n for n in names if results["registrations"][n]["plausibility"]["flags"]}
    deserve = [
        n for n in names if n not in flagged and all((n, m) in decided for m in names if m != n)
    ]
    assert summary["recommended"] == (deserve[0] if deserve else None)
    assert summary["decided"] == bool(deserve)
    assert summary["reason"]
    starred = [
        rid
        for rid, cells in re.findall(r'<tr[^>]* id="(setting-[^"]+)"[^>]*>(.*?)</tr>', raw)
        if "&#9733; recommended" in cells
    ]
    assert starred == ["setting-" + n.replace(":", "-") for n in deserve]


@pytest.mark.parametrize(
    "param, message",
    [
        ("smoothing=1,2", "--param smoothing: not an option of method 'fluid'"),
        ("smoothing_mm=-1,2", "smoothing_mm must be finite numbers > 0"),
        ("smoothing_mm=2,2", "--param smoothing_mm: a value is given twice"),
        ("smoothing_mm", "--param: expected NAME=VALUE"),
        ("iterations=10:5", "shrink_factors and iterations need the same number of levels"),
    ],
)
def test_bad_parameter_is_one_line_before_any_registration(
    population, tmp_path, capsys, param, message
):
    out = tmp_path / "sweep"
    args = ["sweep", "--from", str(population), "--method", "fluid", "--param", param]
    code = main([*args, "--out", str(out), "--quiet"])
    assert code == 2
    assert_one_line(capsys.readouterr().err, message)
    assert not (out / "registrations").exists()


def test_parse_parameter():
    assert parse_parameter("grid_spacing=8,16.5") == ("grid_spacing", (8, 16.5))
    assert parse_parameter("iterations=100:60:40, 50:30:20") == (
        "iterations",
        ((100, 60, 40), (50, 30, 20)),
    )
    assert parse_parameter("metric=mattes,correlation") == ("metric", ("mattes", "correlation"))
    with pytest.raises(nr.InputError, match="no value"):
        parse_parameter("levels=")


def test_an_option_the_engine_cannot_honour_is_refused_before_any_registration(
    population, tmp_path, capsys
):
    out = tmp_path / "sweep"
    args = ["sweep", "--from", str(population), "--method", "pairwise", "--engine", "simpleitk"]
    args += ["--param", "bending_weight=0,0.5", "--out", str(out), "--quiet"]
    assert main(args) == 2
    assert_one_line(
        capsys.readouterr().err,
        "--param bending_weight=0.5: pairwise options: bending_weight needs the elastix engine",
    )
    assert not (out / "registrations").exists()


def test_a_flagged_setting_is_never_recommended_even_when_decided_best(tmp_path):
    """The verdict decides `truth` better than every other registration; flagged
    implausible (a flag the thresholds could raise on any setting), it is not recommended,
    and the reason says so. Unflagged, it is."""
    import dataclasses

    from test_evaluate import make_case

    from itk_nrreval.evaluation import verdict
    from itk_nrreval.experiments.sweep import _recommendation

    make_case(tmp_path)
    result = nr.evaluate(tmp_path / "manifest.yaml", n_samples=3000, seed=2, progress=False)
    assert result.verdict.decided and result.verdict.best == ("truth",)
    assert _recommendation(result)[0] == "truth"
    flag = "SDlogJ 0.90 is 3.0x the median of the registrations compared (0.30)"
    scores = dict(result.scores)
    scores["truth"] = dataclasses.replace(scores["truth"], flags=(flag,))
    v = verdict(scores, result.comparisons, has_labels=True)
    assert v.decided and v.best == ("truth",)  # a flag decides nothing
    flagged = dataclasses.replace(result, scores=scores, verdict=v)
    recommended, reason = _recommendation(flagged)
    assert recommended is None
    assert "truth" in reason and "flagged implausible" in reason and flag in reason
