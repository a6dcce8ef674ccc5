"""The HTML report's flagged subjects (issue 27): each registration's section opens with the
subjects that failed under it -- name, flags, diagnosis, and the subject beside the mean
image -- ``subjects.png`` plots every subject's z-score, and the subjects left off the
common grid are named in the verdict area.

A real evaluate run on a small generated cohort (data_synth) with known damages
(data_synth.damage); the subject's picture is checked against an independent SimpleITK
resampling of its image through its transform file.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import SimpleITK as sitk
from matplotlib.colors import to_rgba
from test_html_report import _Page, check_png, check_self_contained, decode_png, parse
from test_report_browser import measure_layout, needs_browser, overflows

import itk_nrreval as nr
from data_synth import make_population
from data_synth.damage import write_damaged
from itk_nrreval.report import evaluation_page
from itk_nrreval.report._plot import middle_slice, thumbnail
from itk_nrreval.report.evaluation_figures import subject_figure

N = 16
DAMAGES = {2: "mirrored", 7: "duplicated", 15: "off_grid"}
#: Subject 7 is a copy of subject 6: the pair is flagged.
FLAGGED = [2, 6, 7, 15]


@pytest.fixture(scope="module")
def damaged(tmp_path_factory):
    folder = tmp_path_factory.mktemp("subject_report")
    pop = make_population("phantom", dim=2, n=N, seed=4, size=40)
    _, manifest = write_damaged(pop, folder, DAMAGES)
    out = folder / "out"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # off-grid and flagged-registration warnings
        result = nr.evaluate(manifest, n_samples=300, confidence=False, progress=False)
    result.write(out)
    return folder, out, result


def _section(raw: str, sid: str) -> _Page:
    """The parsed text of one section of the page."""
    start = raw.index(f'<section id="{sid}">')
    page = _Page()
    page.feed(raw[start : raw.index("</section>", start)])
    page.close()
    return page


def _words(page: _Page) -> str:
    return " ".join(" ".join(page.text).split())


def test_the_fixture_flags_the_damaged_subjects(damaged):
    _, _, result = damaged
    subjects = result.scores["damaged"].subjects
    assert [q.index for q in subjects if q.flags] == FLAGGED
    assert result.options["left_out_of_scores"] == [15]


def test_the_registration_section_opens_with_its_flagged_subjects(damaged):
    _, out, result = damaged
    page, raw = parse(out / "report.html")
    check_self_contained(page, raw)  # every picture decodes whole
    section = _section(raw, "reg-damaged")
    text = _words(section)
    assert f"{len(FLAGGED)} of the {N} subjects flagged" in text
    # before the registration's own figures
    assert text.index("flagged") < text.index("checkerboard of two subjects")
    subjects = result.scores["damaged"].subjects
    at = {i: text.index(f"subject {i} (s{i:02d}.nii.gz") for i in FLAGGED if i != 7}
    # worst first: by concern (a weighted mean of each subject's signed z-scores), ties by index
    assert sorted(at, key=at.get) == sorted(at, key=lambda i: (-subjects[i].concern, i))
    assert "subject 7 (s07_copy.nii.gz" in text
    for i in FLAGGED:
        q = subjects[i]
        assert " ".join(q.diagnosis.split()) in text, i
        for flag in q.flags:
            assert " ".join(flag.split()) in text, (i, flag)
    assert "Subject flags:" in text and "Registration flag" not in text  # none shared
    # one picture per flagged subject besides the registration's two
    pictures = [decode_png(src) for src in section.srcs]
    assert len(pictures) == 2 + len(FLAGGED)
    for png in pictures:
        check_png(png)
    assert "more" not in text.split("checkerboard of two subjects")[0]


def test_the_subjects_picture_is_its_resampled_image_beside_the_mean(damaged):
    folder, _, result = damaged
    name, i = "damaged", 2
    template = sitk.ReadImage(str(folder / "truth/template.nii.gz"))
    transform = sitk.ReadTransform(str(folder / "damaged/s02_mirrored.h5"))
    image = sitk.ReadImage(str(folder / "img/s02.nii.gz"), sitk.sitkFloat64)
    expected = sitk.GetArrayFromImage(
        sitk.Resample(image, template, transform, sitk.sitkLinear, 0.0)
    )
    fig = subject_figure(result, name, i)
    subject, mean, checker = (np.asarray(ax.images[0].get_array()) for ax in fig.axes[:3])
    inside = np.isfinite(subject)
    assert inside.mean() > 0.5
    np.testing.assert_allclose(subject[inside], thumbnail(expected)[inside], atol=1e-3)
    np.testing.assert_allclose(mean, thumbnail(middle_slice(result.mean_images[name])))
    # the checkerboard takes each pixel from one of the two, both present
    from_subject = np.isclose(checker, subject) | (np.isnan(checker) & np.isnan(subject))
    from_mean = np.isclose(checker, mean)
    assert np.all(from_subject | from_mean)
    assert (from_subject & ~from_mean).any() and (from_mean & ~from_subject).any()
    assert "subject 2" in fig.axes[0].get_title() and "mean" in fig.axes[1].get_title()


def test_resampled_slices_are_kept_for_flagged_subjects_only(damaged):
    _, _, result = damaged
    kept = sorted(int(k.split("_")[1]) for k in result.thumbnails["damaged"] if k[:6] == "image_")
    assert kept == sorted({0, 1, *FLAGGED})


def test_subjects_png_plots_every_z_score_with_the_threshold(damaged):
    from itk_nrreval.report.evaluation_figures import _subjects_figure

    _, out, result = damaged
    png = (out / "subjects.png").read_bytes()
    page, _ = parse(out / "report.html")
    assert png in {decode_png(src) for src in page.srcs}
    check_png(png)
    fig = _subjects_figure(result, ["damaged"])
    [ax] = fig.axes
    threshold = result.options["subject_thresholds"]["outlier_z"]
    lines = [ln for ln in ax.get_lines() if set(np.asarray(ln.get_ydata())) == {threshold}]
    assert len(lines) == 1
    # every scored subject is a point at its z; the flagged ones in their own colour
    subjects = result.scores["damaged"].subjects
    points = {}
    for coll in ax.collections:
        colour = tuple(to_rgba(coll.get_facecolors()[0]))
        for _, y in coll.get_offsets():
            points.setdefault(colour, []).append(float(y))
    assert len(points) == 2
    flagged_colour = next(c for c, ys in points.items() if len(ys) == len(FLAGGED) - 1)
    expected_flagged = sorted(subjects[i].z for i in FLAGGED if subjects[i].z is not None)
    assert sorted(points[flagged_colour]) == pytest.approx(expected_flagged)
    others = [q.z for q in subjects if not q.flags]
    [rest] = [ys for c, ys in points.items() if c != flagged_colour]
    assert sorted(rest) == pytest.approx(sorted(others))
    assert "left out" in ax.get_title() and "1 subject" in ax.get_title()


def test_the_verdict_area_names_the_subjects_left_off_the_grid(damaged):
    _, out, _ = damaged
    _, raw = parse(out / "report.html")
    text = _words(_section(raw, "verdict"))
    assert "off the common grid" in text and "subject 15 (s15.nii.gz)" in text
    assert "4 of 16 subjects flagged" in text


def test_flagged_subjects_beyond_the_shown_ones_are_counted(damaged, monkeypatch):
    _, _, result = damaged
    monkeypatch.setattr(evaluation_page, "FLAGGED_SUBJECTS_SHOWN", 2)
    raw = evaluation_page.report_html(result)
    section = _section(raw, "reg-damaged")
    text = _words(section)
    assert len(section.srcs) == 2 + 2
    assert "2 more flagged subjects" in text and "subjects.csv" in text
    # the two of highest concern are shown; the others only in the ranked list below
    subjects = result.scores["damaged"].subjects
    worst = sorted(FLAGGED, key=lambda i: (-subjects[i].concern, i))
    shown = text.split("2 more flagged subjects")[0]
    names = {i: f"subject {i} (s{i:02d}{'_copy' if i == 7 else ''}.nii.gz)" for i in FLAGGED}
    assert all(names[i] in shown for i in worst[:2])
    assert not any(names[i] in shown for i in worst[2:])


def test_every_subject_is_listed_worst_first_by_concern(damaged):
    """Issue 42: the registration's section ranks every subject by its concern, the first
    ten in a table and the others in a closed list, worst first, the reference-free cohort
    all judged; a flagged subject's row says how many subject flags it has."""
    import re

    _, out, result = damaged
    _, raw = parse(out / "report.html")
    section = raw[raw.index('<section id="reg-damaged">') :]
    ranked_part = section[
        section.index("Every subject, worst first") : section.index(
            "Scores, images and deformation"
        )
    ]
    listed = [
        int(i) for i in re.findall(r"<td>\d+</td><td class=\"text\">subject (\d+) ", ranked_part)
    ]
    subjects = result.scores["damaged"].subjects
    assert sorted(listed) == list(range(N))
    concern = [subjects[i].concern for i in listed]
    assert concern == sorted(concern, reverse=True)
    closed = ranked_part[ranked_part.index("<details>") :]
    assert f"The other {N - 10} subjects" in closed
    assert len(re.findall(r"subject \d+ ", closed)) == N - 10
    for i in FLAGGED:
        flags = len(subjects[i].flags)
        row = re.search(rf"subject {i} \(.*?</tr>", ranked_part).group(0)
        assert f"{flags} subject flag" in row


@needs_browser
def test_report_with_flagged_subjects_fits_a_1280_px_window(damaged, tmp_path):
    _, out, _ = damaged
    report = measure_layout(out / "report.html", tmp_path)
    assert overflows(report) == []
