"""Issue 46 (item 2): label names from a BIDS dseg.tsv, a FreeSurfer lookup table or the
manifest, shown beside the values in results.json, metrics.csv, the report and
``nrreval overlap``."""

from __future__ import annotations

import csv
import json
import warnings

import pytest
import yaml
from test_evaluate import make_case

import itk_nrreval as nr
from itk_nrreval import InputError
from itk_nrreval.cli import main
from itk_nrreval.io.label_names import label_names_from, label_text, read_label_names
from itk_nrreval.io.manifest import load_manifest

DSEG = "index\tname\tabbreviation\n1\tgrey matter\tGM\n2\twhite matter\tWM\n3\tCSF\tCSF\n"
LUT = """\
#$Id: FreeSurferColorLUT.txt
#No. Label Name:                            R   G   B   A

0   Unknown                                 0   0   0   0
2   Left-Cerebral-White-Matter            245 245 245   0   # a trailing comment
17  Left-Hippocampus                      220 216  20   0
"""


def test_a_bids_dseg_tsv_is_read_by_its_columns(tmp_path):
    path = tmp_path / "desc-aseg_dseg.tsv"
    # the columns in another order, and an extra one, as BIDS allows
    path.write_text("name\tcolor\tindex\nbackground\t#000000\t0\nleft hippocampus\t#dcd814\t17\n")
    assert read_label_names(path) == {0: "background", 17: "left hippocampus"}
    (tmp_path / "dseg.tsv").write_text(DSEG)
    assert read_label_names(tmp_path / "dseg.tsv") == {
        1: "grey matter",
        2: "white matter",
        3: "CSF",
    }


def test_a_freesurfer_lookup_table_is_read_skipping_comments(tmp_path):
    path = tmp_path / "FreeSurferColorLUT.txt"
    path.write_text(LUT)
    assert read_label_names(path) == {
        0: "Unknown",
        2: "Left-Cerebral-White-Matter",
        17: "Left-Hippocampus",
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("index\tlabel\n1\tgm\n", "needs the columns 'index' and 'name' (missing 'name')"),
        ("index\tname\none\tgm\n", "line 2: index 'one' is not an integer"),
        ("index\tname\n1\tgm\n1\twm\n", "line 3: duplicate index 1"),
        ("1 gm 0 0 0 0\n2.5 wm 0 0 0 0\n", "line 2: index '2.5' is not an integer"),
        ("# only a comment\n", "no label names"),
    ],
)
def test_a_malformed_table_is_one_line_naming_the_file(tmp_path, text, message):
    path = tmp_path / "bad_dseg.tsv"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        read_label_names(path)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value)
    assert "\n" not in str(err.value)


def test_a_mapping_and_the_text_beside_a_value(tmp_path):
    assert label_names_from({1: "gm", "2": "wm"}) == {1: "gm", 2: "wm"}
    with pytest.raises(InputError, match="key 'x' is not an integer"):
        label_names_from({"x": "gm"})
    with pytest.raises(InputError, match="label 1 has no name"):
        label_names_from({1: " "})
    assert label_text(2, {2: "wm"}) == "2 (wm)" and label_text(3, {2: "wm"}) == "3"
    assert label_text(3, None) == "3"


def test_the_manifest_reads_label_names_and_reports_a_bad_table(tmp_path):
    data = make_case(tmp_path)
    (tmp_path / "dseg.tsv").write_text(DSEG)
    m = load_manifest({**data, "label_names": "dseg.tsv"}, base_dir=tmp_path, check_files=False)
    assert m.label_names == {1: "grey matter", 2: "white matter", 3: "CSF"}
    assert m.describe()["label_names"]["3"] == "CSF"
    assert load_manifest(data, base_dir=tmp_path, check_files=False).label_names is None
    m = load_manifest(
        {**data, "label_names": {1: "a", 2: "b"}}, base_dir=tmp_path, check_files=False
    )
    assert m.label_names == {1: "a", 2: "b"}
    (tmp_path / "bad.tsv").write_text("index\tname\n1\tgm\n1\twm\n")
    with pytest.raises(InputError, match=r"bad\.tsv: line 3: duplicate index 1"):
        load_manifest({**data, "label_names": "bad.tsv"}, base_dir=tmp_path, check_files=False)


def _evaluate(folder, figures=True):
    """Evaluate ``folder/manifest.yaml`` quickly into ``folder/out``; return that folder."""
    out = folder / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nr.evaluate(
            folder / "manifest.yaml",
            n_samples=200,
            confidence=False,
            inverse_consistency=False,
            progress=False,
        )
    result.write(out, figures=figures)
    return out


def test_an_evaluation_shows_the_dseg_names_in_results_metrics_and_report(tmp_path):
    data = make_case(tmp_path)
    (tmp_path / "dseg.tsv").write_text(DSEG)
    data["label_names"] = "dseg.tsv"
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    out = _evaluate(tmp_path)
    res = json.loads((out / "results.json").read_text())
    labels = res["registrations"]["truth"]["label_metrics"]["labels"]
    assert {v: e["name"] for v, e in labels.items()} == {
        "1": "grey matter",
        "2": "white matter",
        "3": "CSF",
    }
    rows = list(csv.DictReader(open(out / "metrics.csv", newline="")))
    header = list(rows[0])
    assert header[header.index("label") + 1] == "label_name"
    named = {(r["registration"], r["label"]): r["label_name"] for r in rows}
    assert named[("truth", "3")] == "CSF" and named[("identity", "1")] == "grey matter"
    assert named[("truth", "all")] == ""
    html = (out / "report.html").read_text()
    assert "2 (white matter)" in html and "3 (CSF)" in html


def test_without_names_the_values_as_before(tmp_path):
    make_case(tmp_path)
    out = _evaluate(tmp_path, figures=False)  # what is checked: results.json, metrics.csv
    res = json.loads((out / "results.json").read_text())
    assert "name" not in res["registrations"]["truth"]["label_metrics"]["labels"]["1"]
    assert "label_name" not in (out / "metrics.csv").read_text().splitlines()[0]


def test_nrreval_overlap_shows_the_names(tmp_path, capsys):
    make_case(tmp_path)
    path = tmp_path / "FreeSurferColorLUT.txt"
    path.write_text("1 grey 0 0 0 0\n2 white 0 0 0 0\n")
    table = tmp_path / "table.csv"
    labels = [str(tmp_path / f"lab{i}.nii.gz") for i in range(3)]
    code = main(["overlap", *labels, "--label-names", str(path), "--table", str(table), "--quiet"])
    assert code == 0
    assert "white" in capsys.readouterr().out
    rows = list(csv.DictReader(open(table, newline="")))
    assert list(rows[0])[:2] == ["label", "label_name"]
    assert [r["label_name"] for r in rows] == ["grey", "white", ""]
    # the table written with names is still ours to replace
    assert main(["overlap", *labels, "--label-names", str(path), "--table", str(table)]) == 0


def test_the_contour_legend_names_the_labels():
    import numpy as np
    from matplotlib.figure import Figure

    from itk_nrreval.report._plot import draw_label_contours
    from itk_nrreval.report.evaluation_figures import _label_order

    lab = np.zeros((20, 20), int)
    lab[2:8, 2:8], lab[10:18, 10:18] = 3, 12
    handles, _ = draw_label_contours(Figure().subplots(), lab, names={3: "CSF"})
    assert [h.get_label() for h in handles] == ["3 (CSF)", "12"]
    assert sorted(["12 (b)", "3 (CSF)", "2"], key=_label_order) == ["2", "3 (CSF)", "12 (b)"]


def test_bids_derivatives_take_the_names_from_a_dseg_tsv(tmp_path):
    from test_derivatives import NO_SESSIONS, SPACE, anat, write_tree

    from data_synth import make_population

    pop = make_population("phantom", dim=2, n=3, seed=4, spacing=4.0, size=(52, 60))
    root = write_tree(tmp_path / "d", pop, version="1.0", keys=NO_SESSIONS[:3])
    assert nr.manifest_from_derivatives([root], space=SPACE).label_names is None
    (root / "desc-aseg_dseg.tsv").write_text(DSEG)  # at the dataset's root
    found = nr.manifest_from_derivatives([root], space=SPACE)
    assert found.label_names == {1: "grey matter", 2: "white matter", 3: "CSF"}
    folder, stem = anat(root, "01")
    (folder / f"{stem}_dseg.tsv").write_text("index\tname\n1\tgm\n")  # beside the label maps
    assert nr.manifest_from_derivatives([root], space=SPACE).label_names == {1: "gm"}
