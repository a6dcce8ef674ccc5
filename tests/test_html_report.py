"""The HTML report: self-contained, complete, light; and the small arrays it draws, checked
against independent computations (resampling, Jacobians and histograms done here with
SimpleITK and numpy)."""

from __future__ import annotations

import base64
import io
import math
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import test_evaluate
import yaml
from test_evaluate import make_case

import itk_nrreval as nr
from itk_nrreval.io._images import Geometry
from itk_nrreval.io.plausibility import (
    LOG_JACOBIAN_BINS,
    LOG_JACOBIAN_RANGE,
    deformation_measures,
    deformation_plausibility,
)
from itk_nrreval.io.transforms import field_transform
from itk_nrreval.report import FLAGGED_SUBJECTS_SHOWN, format_number
from itk_nrreval.report._plot import thumbnail
from itk_nrreval.report.evaluation_figures import figure_pngs

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class _Page(HTMLParser):
    """Everything the checks need from a page: tags, ids, links, images, text."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.tags: list[str] = []
        self.ids: set[str] = set()
        self.hrefs: list[str] = []
        self.srcs: list[str] = []
        self.attr_values: list[str] = []
        self.sections: dict[str, str] = {}  # section id -> text of its first h2
        self.text: list[str] = []
        self._section: str | None = None
        self._in_h2 = False
        self._h2: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        a = dict(attrs)
        self.attr_values += [v for v in a.values() if v is not None]
        if "id" in a:
            self.ids.add(a["id"])
        if tag == "a" and "href" in a:
            self.hrefs.append(a["href"])
        if tag == "img":
            self.srcs.append(a.get("src", ""))
        if tag == "section":
            self._section = a.get("id")
        if tag == "h2" and self._section is not None and self._section not in self.sections:
            self._in_h2, self._h2 = True, []

    def handle_endtag(self, tag):
        if tag == "h2" and self._in_h2:
            self.sections[self._section] = "".join(self._h2)
            self._in_h2 = False

    def handle_data(self, data):
        self.text.append(data)
        if self._in_h2:
            self._h2.append(data)


def parse(path: Path) -> tuple[_Page, str]:
    raw = path.read_text(encoding="utf-8")
    page = _Page()
    page.feed(raw)
    page.close()
    return page, raw


def decode_png(src: str) -> bytes:
    prefix = "data:image/png;base64,"
    assert src.startswith(prefix), src[:60]
    data = base64.b64decode(src[len(prefix) :], validate=True)
    assert data[:8] == PNG_SIGNATURE
    return data


def check_png(data: bytes) -> tuple[int, int]:
    """A whole, drawn PNG: its chunks' checksums hold, it decodes to the size its header
    states, and it is not blank. Returns (width, height)."""
    from PIL import Image

    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    with Image.open(io.BytesIO(data)) as im:
        assert im.format == "PNG"
        im.verify()  # CRC of every chunk
    with Image.open(io.BytesIO(data)) as im:
        pixels = np.asarray(im.convert("RGB"))
    assert pixels.shape == (height, width, 3)
    assert width > 20 and height > 20
    # distinct colours, each RGB triple as one integer: np.unique(axis=0) on the (h*w, 3)
    # rows gave the same count at 70x the time (seconds per report)
    rgb = pixels.astype(np.uint32)
    colours = np.unique((rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2])
    assert len(colours) > 2, "a blank picture"
    return width, height


def subject_pictures(result) -> int:
    """How many flagged subjects' pictures the report shows: at most
    FLAGGED_SUBJECTS_SHOWN per registration."""
    return sum(min(len(s.flagged_subjects), FLAGGED_SUBJECTS_SHOWN) for s in result.scores.values())


def stability_figures(result) -> int:
    """The rank-stability blob plot and the significance map: two summary figures more
    with subject-level confidence (issue 45)."""
    return 2 if result.rank_stability and len(result.names) > 1 else 0


def check_self_contained(page: _Page, raw: str) -> None:
    """No external reference of any kind, no script, every internal link resolves."""
    assert "http://" not in raw and "https://" not in raw and "file:" not in raw
    assert "script" not in page.tags and "link" not in page.tags
    assert "iframe" not in page.tags and "object" not in page.tags and "embed" not in page.tags
    assert "@import" not in raw and "url(" not in raw
    for v in page.attr_values:
        if v.startswith("data:image/png;base64,"):
            continue
        assert not v.startswith("//") and "://" not in v, v
    for href in page.hrefs:
        assert href.startswith("#"), href
        assert href[1:] in page.ids, f"link to a missing id: {href}"
    for src in page.srcs:
        check_png(decode_png(src))


# ----------------------------------------------------------------------------- 2D, labels


@pytest.fixture(scope="module")
def case2d(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("html2d")
    make_case(tmp)
    out = tmp / "out"
    result = nr.evaluate(tmp / "manifest.yaml", n_samples=1000, progress=False)
    result.write(out)
    return tmp, out, result


def test_report_is_self_contained_and_complete(case2d):
    _, out, result = case2d
    page, raw = parse(out / "report.html")
    check_self_contained(page, raw)
    text = " ".join(" ".join(page.text).split())
    # the verdict in words, before the table
    for line in result.verdict.text:
        assert " ".join(line.split()) in text
    assert text.index(" ".join(result.verdict.text[0].split())) < text.index("Generalization")
    # every registration has its own section, headed by its name
    for name in result.names:
        heads = [h for h in page.sections.values() if h.strip().startswith(f"Registration: {name}")]
        assert len(heads) == 1, name
    for sid in ("verdict", "scores", "figures", "plausibility", "frames", "inputs", "options"):
        assert sid in page.sections
    # the legend defines what the columns are
    for words in ("not a rank", "(worst − x) / (worst − best)", "intensity units", "Monte-Carlo"):
        assert words in text, words
    assert "jackknife" in text and "Tanimoto" in text and "higher is better" in text
    # a bounded number of pictures: 4 summary figures + 2 per registration + its flagged
    # subjects, at most FLAGGED_SUBJECTS_SHOWN
    pictures = subject_pictures(result) + stability_figures(result)
    assert len(page.srcs) == 4 + 2 * len(result.names) + pictures
    # the summary figures embedded are the very files written beside the report
    embedded = {decode_png(src) for src in page.srcs}
    for fname in (
        "specificity.png",
        "specificity_vs_overlap.png",
        "mean_images.png",
        "subjects.png",
    ):
        assert (out / fname).read_bytes() in embedded
    # each flag (none here) and each frame spread is printed
    for name in result.names:
        f = result.scores[name].frame
        assert format_number(f.spread_mean_mm, 3) in text


def test_figures_are_rendered_the_same_way_twice(case2d):
    _, out, result = case2d
    again = figure_pngs(result)
    assert again["specificity.png"] == (out / "specificity.png").read_bytes()


def test_thumbnails_match_an_independent_resampling(case2d):
    tmp, _, result = case2d
    th = result.thumbnails["truth"]
    size = test_evaluate.SIZE
    # truth is the common frame: subject i resampled = image i through truth_i on the template
    template = sitk.ReadImage(str(tmp / "template.nii.gz"))
    for i in (0, 1):
        t = field_transform(sitk.ReadImage(str(tmp / f"truth{i}_1Warp.nii.gz")))
        img = sitk.Resample(
            sitk.ReadImage(str(tmp / f"img{i}.nii.gz"), sitk.sitkFloat64),
            template,
            t,
            sitk.sitkLinear,
            0.0,
        )
        expected = sitk.GetArrayFromImage(img)
        got = th[f"image_{i}"]
        assert got.shape == (size, size)
        inside = np.isfinite(got)
        assert inside.mean() > 0.9
        np.testing.assert_allclose(got[inside], expected[inside], rtol=1e-5, atol=1e-3)
    # labels: the dominant linearly resampled membership ~ nearest-neighbour resampling
    t0 = field_transform(sitk.ReadImage(str(tmp / "truth0_1Warp.nii.gz")))
    nearest = sitk.GetArrayFromImage(
        sitk.Resample(
            sitk.ReadImage(str(tmp / "lab0.nii.gz")), template, t0, sitk.sitkNearestNeighbor, 0
        )
    )
    labels = th["labels_0"]
    assert labels.shape == (size, size) and labels.dtype.kind == "i"
    assert set(np.unique(labels)) == set(np.unique(nearest)) == {0, 1, 2, 3}
    assert np.mean(labels == nearest) > 0.95


def _det_j_2d(u: np.ndarray, spacing=(1.0, 1.0)) -> np.ndarray:
    """det(I + du/dx) of a field u (numpy (y, x, 2), components (x, y)); central differences
    inside, one-sided at the border (numpy.gradient), identity direction."""
    dux_dy, dux_dx = np.gradient(u[..., 0], spacing[1], spacing[0])
    duy_dy, duy_dx = np.gradient(u[..., 1], spacing[1], spacing[0])
    return (1 + dux_dx) * (1 + duy_dy) - dux_dy * duy_dx


def test_jacobian_map_and_histogram_match_numpy(case2d):
    tmp, _, result = case2d
    th = result.thumbnails["truth"]
    n = test_evaluate.N_IMAGES
    dets = [
        _det_j_2d(sitk.GetArrayFromImage(sitk.ReadImage(str(tmp / f"truth{i}_1Warp.nii.gz"))))
        for i in range(n)
    ]
    np.testing.assert_allclose(th["detj_0"], dets[0], rtol=0, atol=1e-6)
    logs = np.log(np.concatenate([d.ravel() for d in dets]))
    assert np.all(np.isfinite(logs))  # nothing folds in this case
    counts, edges = np.histogram(logs, bins=64, range=(-2.0, 2.0))
    np.testing.assert_array_equal(th["log_jacobian_counts"], counts)
    np.testing.assert_allclose(th["log_jacobian_edges"], edges)
    below, above, folded = th["log_jacobian_outside"]
    assert (below, above, folded) == (np.sum(logs < -2), np.sum(logs > 2), 0)
    assert th["log_jacobian_counts"].sum() + below + above + folded == n * test_evaluate.SIZE**2
    # an identity (affine) registration: det J = 1 everywhere, all in the bin holding 0
    ident = result.thumbnails["identity"]
    np.testing.assert_allclose(ident["detj_0"], 1.0, atol=1e-9)
    k = int(np.searchsorted(edges, 0.0, side="right")) - 1
    assert ident["log_jacobian_counts"][k] == ident["log_jacobian_counts"].sum()


def test_specificity_figure_says_when_monte_carlo_bars_hide(tmp_path):
    import dataclasses

    from itk_nrreval.report.evaluation_figures import _specificity_figure

    make_case(tmp_path, with_labels=False)
    result = nr.evaluate(
        tmp_path / "manifest.yaml", n_samples=30_000, progress=False, confidence=False
    )
    names = list(result.verdict.ranking)
    title = _specificity_figure(result, names).axes[0].get_title()
    assert "M = 30,000" in title and "L1" in title and "Monte-Carlo" in title
    mc = max(result.scores[n].specificity.stderr for n in names)
    values = [s.specificity.value for s in result.scores.values()]
    assert 1.96 * mc < 0.01 * (max(values) - min(values))  # invisible at this scale
    assert "smaller than the markers" in title
    # the same scores with a Monte-Carlo error that shows: the note goes
    scores = {
        n: dataclasses.replace(
            s, specificity=dataclasses.replace(s.specificity, stderr=0.05 * max(values))
        )
        for n, s in result.scores.items()
    }
    visible = dataclasses.replace(result, scores=scores)
    title = _specificity_figure(visible, names).axes[0].get_title()
    assert "smaller than the markers" not in title and "95% Monte-Carlo interval" in title
    # without labels: no overlap figure, no contours, and the report still holds
    result.write(tmp_path / "out")
    page, raw = parse(tmp_path / "out" / "report.html")
    check_self_contained(page, raw)
    pictures = subject_pictures(result) + stability_figures(result)
    assert len(page.srcs) == 3 + 2 * len(names) + pictures
    assert "Monte-Carlo intervals only" in " ".join(page.text)


# ----------------------------------------------------------------------------- size with N


def test_report_size_grows_sublinearly_with_n(case2d, tmp_path, monkeypatch):
    # N = 6: the module's case (make_case, M = 1000); N = 12: the same case with twice the
    # images, evaluated the same way
    _, out, result = case2d
    assert len(result.inputs["images"]) == test_evaluate.N_IMAGES == 6
    sizes = {6: (out / "report.html").stat().st_size}
    monkeypatch.setattr(test_evaluate, "N_IMAGES", 12)
    make_case(tmp_path)
    nr.evaluate(tmp_path / "manifest.yaml", n_samples=1000, progress=False).write(tmp_path / "o")
    sizes[12] = (tmp_path / "o" / "report.html").stat().st_size
    assert sizes[6] < 2_000_000
    assert sizes[12] < 1.3 * sizes[6], sizes  # twice the images, about the same report


# ----------------------------------------------------------------------------- 3D


SHAPE3 = (12, 14, 16)  # numpy (z, y, x)


def _field3(seed: int, amplitude: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z, y, x = (np.indices(SHAPE3) / (np.array(SHAPE3)[:, None, None, None] - 1)).astype(float)
    bump = np.sin(np.pi * x) * np.sin(np.pi * y) * np.sin(np.pi * z)
    u = np.zeros((*SHAPE3, 3))
    for c in range(3):
        a, b = rng.uniform(-1, 1, 2)
        u[..., c] = amplitude * bump * (a * np.sin(np.pi * (x + z)) + b * np.cos(np.pi * y))
    return u


def _image3(arr: np.ndarray, spacing=(1.0, 1.2, 1.5)) -> sitk.Image:
    img = sitk.GetImageFromArray(arr, isVector=arr.ndim == 4)
    img.SetSpacing(spacing)
    return img


@pytest.fixture(scope="module")
def case3d(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("html3d")
    z, y, x = np.indices(SHAPE3).astype(float)
    labels = np.zeros(SHAPE3, np.int16)
    labels[((z - 6) / 4) ** 2 + ((y - 7) / 5) ** 2 + ((x - 8) / 6) ** 2 <= 1] = 1
    labels[((z - 6) / 2) ** 2 + ((y - 6) / 2) ** 2 + ((x - 9) / 2) ** 2 <= 1] = 2
    template = _image3(labels.astype(float) * 50.0)
    sitk.WriteImage(template, str(tmp / "template.nii.gz"))
    data = {"images": [], "labels": [], "registrations": {}}
    fields, idents = [], []
    for i in range(5):
        u = _field3(i, 1.5)
        s_i = sitk.DisplacementFieldTransform(_image3(u))
        img = sitk.Resample(template, template, s_i, sitk.sitkLinear, 0.0)
        lab = sitk.Resample(_image3(labels), template, s_i, sitk.sitkNearestNeighbor, 0)
        sitk.WriteImage(img, str(tmp / f"img{i}.nii.gz"))
        sitk.WriteImage(lab, str(tmp / f"lab{i}.nii.gz"))
        sitk.WriteImage(_image3(u), str(tmp / f"field{i}_1Warp.nii.gz"))
        sitk.WriteTransform(sitk.AffineTransform(3), str(tmp / f"id{i}_0GenericAffine.mat"))
        data["images"].append(f"img{i}.nii.gz")
        data["labels"].append(f"lab{i}.nii.gz")
        fields.append(f"field{i}_1Warp.nii.gz")
        idents.append(f"id{i}_0GenericAffine.mat")
    data["registrations"] = {
        "fields": {"reference": "template.nii.gz", "transforms": fields},
        "identity": {"reference": "img0.nii.gz", "reference_index": 0, "transforms": idents},
    }
    (tmp / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp / "out"
    result = nr.evaluate(tmp / "manifest.yaml", n_samples=500, progress=False)
    result.write(out)
    return tmp, out, result


def test_3d_thumbnails_are_middle_slices(case3d):
    tmp, out, result = case3d
    for name, th in result.thumbnails.items():
        for key in ("image_0", "image_1", "labels_0", "detj_0"):
            assert th[key].ndim == 2, (name, key)
        assert th["image_0"].shape == SHAPE3[1:]
        np.testing.assert_allclose(th["common_spacing"], (1.2, 1.0))
    # det J of subject 0's field on the middle z slice, against numpy on the whole volume
    u = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp / "field0_1Warp.nii.gz")))
    sx, sy, sz = 1.0, 1.2, 1.5
    grads = [np.gradient(u[..., c], sz, sy, sx) for c in range(3)]  # d/dz, d/dy, d/dx
    jac = np.empty((*SHAPE3, 3, 3))
    for c in range(3):
        for d, g in zip((0, 1, 2), (grads[c][2], grads[c][1], grads[c][0]), strict=True):
            jac[..., c, d] = g + (c == d)
    det = np.linalg.det(jac)
    np.testing.assert_allclose(
        result.thumbnails["fields"]["detj_0"], det[SHAPE3[0] // 2], rtol=0, atol=1e-6
    )
    total = sum(int(v) for v in result.thumbnails["fields"]["log_jacobian_outside"])
    assert result.thumbnails["fields"]["log_jacobian_counts"].sum() + total == 5 * math.prod(SHAPE3)
    # the 3D mean image's middle slice is what the report shows
    page, raw = parse(out / "report.html")
    check_self_contained(page, raw)
    pictures = subject_pictures(result) + stability_figures(result)
    assert len(page.srcs) == 4 + 2 * len(result.names) + pictures
    assert (out / "report.html").stat().st_size < 2_000_000


# ----------------------------------------------------------------------------- units


def test_jacobian_summary_is_one_pass_and_independent_of_slabs():
    g = Geometry((20, 18, 30), (1.0, 1.3, 0.9), (3.0, -2.0, 1.0), tuple(np.eye(3).ravel()))
    rng = np.random.default_rng(1)
    u = rng.normal(scale=0.8, size=(*g.shape, 3))  # rough: some voxels fold
    img = sitk.GetImageFromArray(u, isVector=True)
    t = field_transform(g.apply_to(img))
    mask = np.zeros(g.shape, bool)
    mask[3:-2, 2:-3, 1:-1] = True
    whole_measures = deformation_measures(t, g, mask=mask, inverse_consistency=False)
    whole_p, whole = whole_measures.plausibility, whole_measures.jacobian
    slab_measures = deformation_measures(
        t, g, mask=mask, inverse_consistency=False, max_slab_voxels=3 * 20 * 18
    )
    slab_p, slab = slab_measures.plausibility, slab_measures.jacobian
    assert whole_p == deformation_plausibility(t, g, mask=mask, inverse_consistency=False)
    assert slab_p.folded_fraction == whole_p.folded_fraction
    assert slab_p.sdlogj == pytest.approx(whole_p.sdlogj, rel=1e-12)  # merged slab by slab
    np.testing.assert_array_equal(whole.counts, slab.counts)
    np.testing.assert_array_equal(whole.middle, slab.middle)
    assert (whole.below, whole.above, whole.folded) == (slab.below, slab.above, slab.folded)
    n = int(mask.sum())
    assert whole.counts.sum() + whole.below + whole.above + whole.folded == n
    assert whole.folded == round(whole_p.folded_fraction * n) and whole.folded > 0
    assert whole.counts.size == LOG_JACOBIAN_BINS
    np.testing.assert_allclose(whole.edges[[0, -1]], LOG_JACOBIAN_RANGE)
    # the middle slice: NaN outside the mask, det J (unclipped) inside, in range
    mid = whole.middle
    assert mid.shape == g.shape[1:]
    inside = mask[g.shape[0] // 2]
    assert np.all(np.isnan(mid[~inside])) and np.all(np.isfinite(mid[inside]))
    assert whole_p.jacobian_min <= np.nanmin(mid) and np.nanmax(mid) <= whole_p.jacobian_max
    assert np.nanmin(mid) < 0  # folds are shown, not clipped


def test_thumbnail_shrinks_by_whole_factors():
    a = np.arange(600 * 520, dtype=float).reshape(600, 520)
    a[0, 0] = np.nan
    t = thumbnail(a)
    assert max(t.shape) <= 256 and t.shape == (200, 173)  # factor 3; the remainder dropped
    block = [a[i, j] for i in range(3) for j in range(3) if (i, j) != (0, 0)]
    assert t[0, 0] == pytest.approx(sum(block) / 8)
    assert t[1, 2] == pytest.approx(a[3:6, 6:9].mean())
    assert np.isnan(thumbnail(np.full((600, 4), np.nan))).all()
    lab = np.zeros((512, 512), int)
    lab[100:300, 100:300] = 7
    assert set(np.unique(thumbnail(lab, mode="nearest"))) == {0, 7}
    # an image and its label map shrink to the same shape, whatever the remainder
    for shape in [(602, 517), (257, 300), (770, 256)]:
        sizes = {thumbnail(np.zeros(shape), mode=m).shape for m in ("mean", "nearest", "any")}
        assert len(sizes) == 1 and max(sizes.pop()) <= 256, shape
    folded = np.zeros((512, 512), bool)
    folded[5, 5] = True
    assert thumbnail(folded, mode="any").sum() == 1
    small = np.ones((40, 40))
    assert thumbnail(small) is small
    with pytest.raises(ValueError, match="mode"):
        thumbnail(a, mode="max")


def test_png_bytes_keep_the_picture():
    """The compact PNG is the figure matplotlib draws, to 2 levels of 255 per channel."""
    from matplotlib.figure import Figure
    from PIL import Image

    from itk_nrreval.report._plot import png_bytes

    fig = Figure(figsize=(3, 2))
    ax = fig.subplots()
    ax.imshow(np.linspace(0, 1, 200 * 150).reshape(150, 200), cmap="gray")
    ax.plot([0, 199], [0, 149], color="tab:orange")
    ax.set_title("grey ramp and a line")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    reference = np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"), np.int16)
    data = png_bytes(fig, dpi=100)
    assert data[:8] == PNG_SIGNATURE and len(data) < len(buf.getvalue())
    got = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.int16)
    assert got.shape == reference.shape
    assert np.abs(got - reference).max() <= 2


def test_label_contours_have_a_legend_naming_the_values():
    from matplotlib.figure import Figure

    from itk_nrreval.report._plot import LEGEND_LABELS, draw_label_contours

    lab = np.zeros((40, 40), int)
    lab[5:15, 5:15], lab[20:30, 20:35], lab[2:4, 30:38] = 3, 7, 12
    ax = Figure().subplots()
    ax.imshow(np.zeros((40, 40)), cmap="gray", origin="lower")
    handles, title = draw_label_contours(ax, lab)
    assert [h.get_label() for h in handles] == ["3", "7", "12"] and title == "label value"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["3", "7", "12"]
    colours = {tuple(h.get_facecolor()) for h in handles}
    assert len(colours) == 3 and all(not (c[0] == c[1] == c[2]) for c in colours)  # no grey
    many = np.arange(LEGEND_LABELS + 2).repeat(2)[None, :].repeat(4, axis=0)
    handles, title = draw_label_contours(Figure().subplots(), many)
    assert len(handles) == 1 and title == f"labels 1..{LEGEND_LABELS + 1}"


# ----------------------------------------------------------------------------- PNGs, legends


def test_every_embedded_png_decodes_whole(case2d):
    """Each data: URI is base64 of a PNG whose chunks check out and that decodes to the
    size its header states; a corrupted one is caught."""
    _, out, _ = case2d
    page, _ = parse(out / "report.html")
    assert page.srcs
    sizes = [check_png(decode_png(src)) for src in page.srcs]
    assert all(w <= 1400 for w, _ in sizes)  # thumbnails and figures, not full volumes
    data = bytearray(decode_png(page.srcs[0]))
    data[60] ^= 0xFF  # one flipped byte inside the first data chunk
    with pytest.raises(Exception):  # noqa: B017 - PIL raises SyntaxError or OSError
        check_png(bytes(data))


def _legend_labels(legend) -> list[str]:
    return [t.get_text() for t in legend.get_texts()]


def test_label_contour_legends_list_every_label_present(case2d):
    tmp, _, result = case2d
    from itk_nrreval.report.evaluation_figures import _mean_images_figure, images_figure

    # the labels of subject 0, read from its file: the values any resampling can show
    on_disk = {
        int(v) for v in np.unique(sitk.GetArrayFromImage(sitk.ReadImage(str(tmp / "lab0.nii.gz"))))
    }
    on_disk.discard(0)
    for name in result.names:
        shown = {
            int(v)
            for v in np.unique(thumbnail(result.thumbnails[name]["labels_0"], mode="nearest"))
        }
        shown.discard(0)
        assert shown == on_disk, name  # no label lost at this size
        fig = images_figure(result, name)
        legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
        assert len(legends) == 1
        assert _legend_labels(legends[0]) == [str(v) for v in sorted(shown)]
    # one legend for the mean images, naming every label of every panel, each value in one
    # colour in every panel even when a panel lacks another value
    import dataclasses

    names = list(result.names)
    thumbs = {n: dict(t) for n, t in result.thumbnails.items()}
    lab = np.asarray(thumbs[names[1]]["labels_0"]).copy()
    lab[lab == 2] = 0  # panel 2 lacks label 2 ...
    lab[:6, :6] = 9  # ... and has a label 9 of its own
    thumbs[names[1]]["labels_0"] = lab
    fig = _mean_images_figure(dataclasses.replace(result, thumbnails=thumbs), names)
    assert _legend_labels(fig.legends[0]) == [str(v) for v in sorted(on_disk | {9})]
    colours = []
    for ax, n in zip(fig.axes, names, strict=True):
        overlay = np.asarray(ax.images[1].get_array())
        labels = thumbnail(thumbs[n]["labels_0"], mode="nearest")
        drawn = overlay[..., 3] > 0
        colours.append({v: {tuple(c) for c in overlay[drawn & (labels == v)]} for v in (1, 3)})
    for v in (1, 3):
        assert len(colours[0][v]) == 1 and colours[0][v] == colours[1][v], v
