"""The Section IV experiment on generated brain-like data, in a reduced configuration.

The full configuration (12 values of d, 5 repeats, M = 50,000) is benchmarks/bench_validate.py.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from data_synth import perfectly_registered_arrays
from itk_nrreval.cli import main
from itk_nrreval.experiments.perturbation import summarize, validate


@pytest.fixture(scope="module")
def brain():
    return perfectly_registered_arrays("phantom", n=10, seed=0)


@pytest.fixture(scope="module")
def reduced(brain):
    images, labels = brain
    return validate(
        images,
        labels,
        displacements=(0.0, 0.375, 1.0, 2.0, 3.0),
        repeats=2,
        n_samples=5_000,
        weightings=("complexity", "inverse_volume"),
        seed=1,
        progress=False,
    )


def test_specificity_tracks_overlap_on_brain_like_data(brain, reduced):
    images, _ = brain
    assert images.shape == (10, 141, 141)
    res = reduced
    assert len(res.rows) == 10
    m = res.means()
    fit = m["displacement"] >= 0.375
    # specificity rises strictly with d, overlap falls strictly, for d >= 0.375
    assert np.all(np.diff(m["specificity"][fit]) > 0)
    assert np.all(np.diff(m["overlap_complexity"][fit]) < 0)
    assert res.summary.monotonic and res.summary.spearman == pytest.approx(1.0)
    # independent Pearson r over the instances with d >= 0.375
    d = res.column("displacement")
    keep = d >= 0.375
    for w in ("complexity", "inverse_volume"):
        r = np.corrcoef(res.column("specificity")[keep], res.column(f"overlap_{w}")[keep])[0, 1]
        assert res.summary.pearson_r[w] == pytest.approx(r, rel=1e-12)
        assert r <= -0.9
    # the unperturbed set has perfect-registration overlap above every perturbed one
    unperturbed = [row for row in res.rows if row.displacement == 0]
    assert all(row.min_jacobian == 1.0 for row in unperturbed)
    assert (
        min(r.overlap["complexity"] for r in unperturbed)
        > res.column("overlap_complexity")[keep].max()
    )
    # accepted warps never fold
    assert res.column("min_jacobian").min() > 0
    assert res.summary.sensitivity > 10


def test_validation_is_reproducible(brain):
    images, labels = brain
    kw = dict(displacements=(1.0,), repeats=1, n_samples=500, weightings="volume", progress=False)
    a = validate(images[:4], labels[:4], seed=3, **kw)
    b = validate(images[:4], labels[:4], seed=3, n_jobs=1, **kw)
    c = validate(images[:4], labels[:4], seed=4, **kw)
    assert a.rows == b.rows
    # four threads, one image each: they end in any order, and are placed by index
    assert validate(images[:4], labels[:4], seed=3, n_jobs=4, **kw).rows == a.rows
    assert a.rows[0].specificity != c.rows[0].specificity


def test_summary_of_a_handmade_table():
    from itk_nrreval.experiments.perturbation import ValidationRow

    rows = [
        ValidationRow(d, 0, s, 0.5, {"volume": o}, 1.0)
        for d, s, o in [(0.0, 10, 0.9), (0.5, 11, 0.8), (1.0, 13, 0.7), (2.0, 17, 0.5)]
    ]
    s = summarize(rows, ["volume"])
    # fit rows: d = 0.5, 1, 2; slope of s on d by hand: 4 / (7/6)... use the normal equations
    dd, ss = np.array([0.5, 1.0, 2.0]), np.array([11.0, 13.0, 17.0])
    slope = np.sum((dd - dd.mean()) * (ss - ss.mean())) / np.sum((dd - dd.mean()) ** 2)
    assert s.slope == pytest.approx(slope) and s.sensitivity == pytest.approx(slope / 0.5)
    assert s.pearson_r["volume"] == pytest.approx(-1.0) and s.unperturbed == 10
    assert s.spearman == pytest.approx(1.0) and s.monotonic


def test_bad_arguments(brain):
    images, labels = brain
    with pytest.raises(ValueError, match="weighting must be one of"):
        validate(images, labels, weightings=("bogus",), progress=False)
    with pytest.raises(ValueError, match="displacements must be finite numbers >= 0"):
        validate(images, labels, displacements=(-1.0,), progress=False)
    with pytest.raises(ValueError, match="label maps shape"):
        validate(images, labels[:3], progress=False)


def test_cli_synthetic_writes_table_and_figures(tmp_path, capsys):
    out = tmp_path / "val"
    code = main(
        ["validate", "--synthetic", "phantom", "--out", str(out), "--n-images", "4",
         "--displacements", "0,1,2", "--repeats", "1", "--samples", "300",
         "--weighting", "volume", "--no-progress"]
    )  # fmt: skip
    assert code == 0
    for name in ("validation.csv", "validation.json", "validation_fig2.png", "validation_vs_d.png"):
        assert (out / name).stat().st_size > 0
    data = json.loads((out / "validation.json").read_text())
    assert [r["displacement"] for r in data["rows"]] == [0.0, 1.0, 2.0]
    lines = (out / "validation.csv").read_text().splitlines()
    assert lines[0].startswith("displacement,repeat,specificity,specificity_stderr,overlap_volume")
    assert len(lines) == 4
    assert "Pearson r" in capsys.readouterr().out
    assert not math.isnan(data["summary"]["spearman"])


def test_cli_bad_input_is_one_line(tmp_path, capsys):
    code = main(["validate", str(tmp_path / "missing.yaml"), "--out", str(tmp_path)])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("nrreval validate: error:")


def test_report_reads_the_run(reduced, tmp_path):
    """validate's page: self-contained, the verdict in words first, every d a row, both
    figures and Fig. 2 per weighting embedded, the files beside it the same bytes."""
    import dataclasses

    from test_html_report import check_self_contained, decode_png, parse

    from itk_nrreval.experiments.perturbation import OUTPUT_FILES

    written = reduced.write(tmp_path / "v")
    assert [p.name for p in written] == list(OUTPUT_FILES) and "report.html" in OUTPUT_FILES
    page, raw = parse(tmp_path / "v" / "report.html")
    check_self_contained(page, raw)
    text = " ".join(" ".join(page.text).split())
    s = reduced.summary
    r, (lo, hi) = s.pearson_r["complexity"], s.pearson_ci["complexity"]
    assert r < 0 and hi < 0  # brain-like data: the paper's relation holds
    verdict = text.index("Does specificity rise")
    assert "Yes: specificity rises as overlap falls" in text
    assert verdict < text.index("d (px)")
    assert f"{r:.3f}" in text and f"[{lo:.3f}, {hi:.3f}]" in text
    for d in (0.0, 0.375, 1.0, 2.0, 3.0):
        assert "d-" + f"{d:g}".replace(".", "_") in page.ids
    embedded = {decode_png(src) for src in page.srcs}
    assert len(page.srcs) == 3  # Fig. 2 for both weightings, and against d
    for name in ("validation_fig2.png", "validation_vs_d.png"):
        assert (tmp_path / "v" / name).read_bytes() in embedded
    assert "L1 distance, intensity units" in text and "M = 5,000" in text
    # a run where specificity does not follow overlap says so
    wrong = dataclasses.replace(
        s,
        pearson_r={w: 0.4 for w in s.pearson_r},
        pearson_ci={w: (0.1, 0.7) for w in s.pearson_r},
    )
    dataclasses.replace(reduced, summary=wrong).write(tmp_path / "w")
    page, _ = parse(tmp_path / "w" / "report.html")
    assert "No: specificity does not rise as overlap falls" in " ".join(page.text)
