"""The report's layout as a real browser lays it out: headless Chromium in a window 1280 px
wide (less its scroll bar), with the fonts of the machine (DejaVu on Debian), measures the
page itself. Nothing may be wider than the window and no table may scroll sideways inside
its box: the Flags column, the reason a registration is ranked last, must be in view.

Skipped, with the reason, where no Chromium or Chrome is on PATH (``make test`` installs
Debian's ``chromium`` where it can)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from test_evaluate import make_case

import itk_nrreval as nr
from itk_nrreval.io.plausibility import Thresholds

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
WINDOW = (1280, 900)  # CSS pixels, a laptop's browser window

# Run in the page after load: open every <details> (their tables count too), then write what
# the layout engine measured into a <pre> that --dump-dom prints.
_MEASURE = """
<script>
for (const d of document.querySelectorAll('details')) d.open = true;
const report = {
  scrollWidth: document.documentElement.scrollWidth,
  clientWidth: document.documentElement.clientWidth,
  innerWidth: window.innerWidth,
  tables: [...document.querySelectorAll('table')].map(t => {
    const box = t.parentElement;
    return {
      section: (t.closest('section') || {}).id || '',
      table: Math.round(t.getBoundingClientRect().width),
      box: box.clientWidth,
      boxScroll: box.scrollWidth,
    };
  }),
};
const pre = document.createElement('pre');
pre.id = 'layout-measure';
pre.textContent = JSON.stringify(report);
document.body.appendChild(pre);
</script>
"""


def find_browser() -> str | None:
    """The first headless-capable Chromium on PATH, or None."""
    for name in BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    return None


def measure_layout(page: Path, scratch: Path, *, window: tuple[int, int] = WINDOW) -> dict:
    """Lay out a copy of `page` in headless Chromium and return the browser's measurements.

    Parameters
    ----------
    page : Path
        An HTML report; left untouched (a copy with the measuring script is laid out).
    scratch : Path
        An empty folder for the copy and the browser's profile.
    window : (int, int)
        Window width and height in CSS pixels.

    Returns
    -------
    dict
        ``scrollWidth`` (the document's, px), ``innerWidth`` (the window's, px),
        ``clientWidth`` (the window's less its vertical scroll bar, px) and
        ``tables``: per table its ``section`` id, its width ``table``, its container's
        width ``box`` and the container's ``boxScroll`` (> ``box`` when it scrolls).
    """
    browser = find_browser()
    assert browser is not None
    raw = page.read_text(encoding="utf-8")
    copy = scratch / "measured.html"
    copy.write_text(raw.replace("</body>", _MEASURE + "</body>"), encoding="utf-8")
    profile = scratch / "profile"
    profile.mkdir()
    cmd = [
        browser,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
        f"--window-size={window[0]},{window[1]}",
        "--dump-dom",
        copy.as_uri(),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    found = re.search(r'<pre id="layout-measure">(.*?)</pre>', done.stdout, re.S)
    assert found, f"{browser} printed no measurement (exit {done.returncode}): {done.stderr}"
    return json.loads(found.group(1).replace("&quot;", '"').replace("&amp;", "&"))


def overflows(report: dict) -> list[str]:
    """What is wider than the window or its box, in words (empty when everything fits)."""
    out = []
    if report["scrollWidth"] > report["clientWidth"]:
        out.append(f"document {report['scrollWidth']} px > window {report['clientWidth']} px")
    for t in report["tables"]:
        if t["table"] > t["box"] or t["boxScroll"] > t["box"]:
            out.append(f"table in #{t['section']}: {t['table']} px in a {t['box']} px box")
    return out


# names as long as people give them: an algorithm, its options and a date, no spaces
LONG_NAMES = {
    "truth": "groupwise_bspline_elastix_grid8mm_bending0.01_evolving_mean_2024-05-17",
    "perturbed": "pairwise_demons_far_from_mean_reference_sigma3mm_iterations200",
    "identity": "affine_only_baseline_reference_subject_0_no_deformable_stage",
}


@pytest.fixture(scope="module")
def flagged_report(tmp_path_factory) -> Path:
    """An evaluation report with long registration names, every registration flagged for
    folding and roughness (thresholds below anything measured), so every Flags cell is
    long."""
    tmp = tmp_path_factory.mktemp("browser")
    data = make_case(tmp)
    data["registrations"] = {LONG_NAMES[k]: v for k, v in data["registrations"].items()}
    # the truth twice: tied scores, whose cells say so ("rank 1 (tied)"): the demo's report
    # overflowed by 127 px when three of its five registrations were tied
    twin = "groupwise_bspline_elastix_grid_spacing_16mm_bending_weight_0_copy"
    data["registrations"][twin] = data["registrations"][LONG_NAMES["truth"]]
    (tmp / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.warns(RuntimeWarning, match="flagged as implausible"):
        result = nr.evaluate(
            tmp / "manifest.yaml",
            n_samples=500,
            progress=False,
            thresholds=Thresholds(folded_mean=-1.0, sdlogj_ratio=-1.0, sdlogj_floor=-1.0),
        )
    result.write(tmp / "out")
    assert all(len(s.flags) >= 2 for s in result.scores.values()), result.scores
    return tmp / "out" / "report.html"


needs_browser = pytest.mark.skipif(
    find_browser() is None, reason=f"no browser on PATH ({', '.join(BROWSERS)})"
)


@needs_browser
def test_the_measurement_sees_a_table_that_overflows(tmp_path):
    # a table of 2000 px of unbreakable cells, as the report wraps wide tables
    cells = "".join(f"<td style='white-space:nowrap'>{'x' * 20}</td>" for _ in range(20))
    page = tmp_path / "wide.html"
    page.write_text(
        "<!DOCTYPE html><html><body><main style='max-width:600px'>"
        f"<section id='s'><div style='overflow-x:auto'><table><tr>{cells}</tr></table></div>"
        "</section></main></body></html>",
        encoding="utf-8",
    )
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    report = measure_layout(page, scratch)
    [table] = report["tables"]
    assert table["box"] == 600 and table["table"] > 1000 and table["boxScroll"] > 1000
    assert overflows(report) == [f"table in #s: {table['table']} px in a 600 px box"]


@needs_browser
def test_evaluation_report_fits_a_1280_px_window(flagged_report, tmp_path):
    report = measure_layout(flagged_report, tmp_path)
    assert report["innerWidth"] == WINDOW[0] and report["clientWidth"] <= WINDOW[0]
    # the measurement saw the tables, those in closed <details> too
    sections = {t["section"] for t in report["tables"]}
    assert {"scores", "details", "plausibility", "inputs", "options"} <= sections, sections
    assert overflows(report) == []
