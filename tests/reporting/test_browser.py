"""The HTML reports in a real headless browser: every report kind renders, raises no console error, loads its
images and fits a 1280-pixel window (no sideways overflow of the page or of any table). Chromium comes from the
distribution, installed by `make system-deps`, never by a test."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import optuna
import pytest

from mpi_lidar.config import Config
from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.learning.baselines import PAPER_TABLE2, Row, Table2
from mpi_lidar.learning.evaluate import Evaluation, error_metrics
from mpi_lidar.learning.model import load_model
from mpi_lidar.reporting.batch_report import write_batch_report
from mpi_lidar.reporting.cloud_figures import PLOTLY_JS
from mpi_lidar.reporting.report import evaluation_report, write_report
from mpi_lidar.reporting.table2 import table2_report
from mpi_lidar.reporting.tuning_report import tuning_report
from mpi_lidar.scans.store import write_scan
from mpi_lidar.simulation.scenes import cornered_board, flat_wall, render
from mpi_lidar.workflows.bench import BenchPlan, BenchResult, BenchRow, CurvePoint, OutOfRange, write_bench
from mpi_lidar.workflows.correct_archive import correct_archive
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

# One small input per report kind: a batch, a study, a model, about a minute.
pytestmark = [pytest.mark.integration, pytest.mark.slow]

WINDOW_PX = 1280

PROBE = """<script>
window.__problems = [];
window.addEventListener("error", e => window.__problems.push("error: " + (e.message || e.target.src)), true);
const consoleError = console.error;
console.error = (...args) => { window.__problems.push("console: " + args.join(" ")); consoleError(...args); };
window.addEventListener("load", () => setTimeout(() => {
  const width = document.documentElement.clientWidth;
  const box = el => el.getBoundingClientRect();
  const images = [...document.images].map(img => ({src: img.getAttribute("src"), loaded: img.complete &&
    img.naturalWidth > 0, right: box(img).right, shown: box(img).width, natural: img.naturalWidth}));
  const tables = [...document.querySelectorAll("table")].map(t => ({width: box(t).width, right: box(t).right,
    scrolls: t.scrollWidth > t.clientWidth + 1 || t.parentElement.scrollWidth > t.parentElement.clientWidth + 1}));
  const plots = [...document.querySelectorAll(".js-plotly-plot")].map(p => ({right: box(p).right,
    height: box(p).height, svg: p.querySelectorAll(".main-svg").length}));
  const out = document.createElement("pre");
  out.id = "probe";
  const body = getComputedStyle(document.body);
  const content = document.body.clientWidth - parseFloat(body.paddingLeft) - parseFloat(body.paddingRight);
  out.textContent = JSON.stringify({width, content, images, tables, plots, problems: window.__problems,
                                    text: document.body.innerText,
                                    scrollWidth: document.documentElement.scrollWidth});
  document.body.appendChild(out);
}, 500));
</script>"""


@pytest.fixture(scope="session")
def chromium() -> str:
    """The headless browser, installed by the project's set-up (`make system-deps`, run by `make test`)."""
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if not found:
        pytest.fail("chromium is not installed: run `make system-deps` as root (or `apt-get install -y chromium`)",
                    pytrace=False)
    return found


def browse(chromium: str, page: Path, screenshot: Path | None = None, height_px: int = 2000) -> dict:
    """Load a copy of ``page`` (beside its images) with the probe in a 1280-pixel window: the probe's findings,
    and with ``screenshot`` a PNG of the page's first ``height_px`` pixels."""
    probed = page.with_name(f".probed-{page.name}")
    probed.write_text(page.read_text().replace("<head>", "<head>" + PROBE, 1))
    flags = [chromium, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
             "--hide-scrollbars", "--allow-file-access-from-files", "--virtual-time-budget=10000",
             f"--window-size={WINDOW_PX},{height_px}", "--dump-dom"]
    if screenshot is not None:  # the same load draws the screenshot: one browser start a page
        flags.append(f"--screenshot={screenshot}")
    try:
        dom = subprocess.run([*flags, probed.as_uri()], capture_output=True, text=True, timeout=120)
    finally:
        probed.unlink()
    match = re.search(r'<pre id="probe">(.*?)</pre>', dom.stdout, flags=re.S)
    assert match, f"the page did not finish loading: {dom.stderr[-2000:]}"
    text = match.group(1)
    for entity, char in (("&quot;", '"'), ("&lt;", "<"), ("&gt;", ">"), ("&amp;", "&")):
        text = text.replace(entity, char)
    return json.loads(text)


# --- one small input per report kind ----------------------------------------------------------------------

LONG_NAME = "corridor_north_wing_2026-11-25_station_0001"  # long names must wrap, not widen the page


def _no_valid_pixel(name: str):
    """A scan whose every pixel is below the no-light noise: finite depths, no return anywhere."""
    scan = two_path_scan(name, height=12, width=16)
    faint = np.linspace(1e-12, 2e-12, scan.amplitude.size, dtype=np.float32).reshape(scan.amplitude.shape)
    return replace(scan, amplitude=faint)


def _batch(work: Path, model: Path) -> dict[str, Path]:
    """A batch at level full: a corrected scan, a flat wall (nothing corrected), a scan without a valid pixel."""
    scans = work / "scans"
    board = render(cornered_board(height=40, width=56), Config(), np.random.default_rng(3))
    write_scan(replace(board, name=LONG_NAME), scans / f"{LONG_NAME}.scan.zarr")
    wall = render(flat_wall(height=24, width=32), Config(), np.random.default_rng(1))
    write_scan(wall, scans / "flat_wall.scan.zarr")
    write_scan(_no_valid_pixel("dark"), scans / "dark.scan.zarr")
    # no scan grid for a geometric model: the model cannot serve it
    write_scan(replace(wall, name="wall_no_grid", azimuth_rad=None, elevation_rad=None),
               scans / "wall_no_grid.scan.zarr")
    out = work / "batch"
    # Amplitudes in V^2, given: the dark scan's amplitudes are below the no-light noise in that unit.
    outcomes = correct_archive([str(scans)], model, out, CorrectionOptions(gate="geometry", amplitude_scale=1.0),
                               outputs="full")
    statuses = {o.name: o.status for o in outcomes}
    assert statuses[LONG_NAME] == "corrected" and statuses["flat_wall"] == "unchanged", outcomes
    assert statuses["wall_no_grid"] == "unserved", outcomes
    write_batch_report(outcomes, 1.0, out)
    return {"scan-full": out / LONG_NAME / "report.html", "scan-flat-wall": out / "flat_wall" / "report.html",
            "scan-no-valid-pixel": out / "dark" / "report.html", "batch": out / "summary" / "report.html"}


def _light(work: Path, model: Path) -> dict[str, Path]:
    scans = work / "light-scans"
    write_scan(two_path_scan("frame", height=24, width=32), scans / "frame.scan.zarr")
    out = work / "light"
    correct_archive([str(scans)], model, out, CorrectionOptions(gate="all"), outputs="light")
    return {"scan-light": out / "frame" / "report.html"}


def _evaluation(work: Path, model: Path) -> dict[str, Path]:
    rng = np.random.default_rng(0)
    truth = rng.uniform(1.4, 2.4, 2_000)
    raw, corrected = truth + rng.normal(0.01, 0.01, truth.size), truth + rng.normal(0.0, 0.004, truth.size)
    evaluation = Evaluation("runs/quick/dataset.zarr", "test", {
        "raw depth 31.25 MHz": error_metrics(raw, truth), "corrected (XGBoost)": error_metrics(corrected, truth)},
        raw - truth, corrected - truth, "raw depth 31.25 MHz")
    report, figures = evaluation_report(evaluation, load_model(model).card)
    return {"evaluation": write_report(report, work / "evaluation", figures) / "report.html"}


def _tuning(work: Path) -> dict[str, Path]:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="xgboost", sampler=optuna.samplers.TPESampler(seed=0))
    study.optimize(lambda t: 0.006 + 1e-3 * (t.suggest_float("learning_rate", 0.01, 0.3, log=True) - 0.1) ** 2
                   + 1e-4 * t.suggest_int("max_depth", 2, 10) + 1e-5 * t.suggest_float("subsample", 0.5, 1.0),
                   n_trials=12)
    report, figures = tuning_report(study, "sqlite:///runs/quick/optuna.db")
    return {"tuning": write_report(report, work / "tuning", figures) / "report.html"}


def _table2(work: Path) -> dict[str, Path]:
    rows = [Row(name, *(1e-3 * v for v in values[:4]), float(values[4]), 100_000) for name, values in
            PAPER_TABLE2.items()]
    report, figures = table2_report(Table2(rows, ["SVM fitted on 20,000 rows (an RBF SVM is quadratic in rows)."]))
    return {"table2": write_report(report, work / "table2", figures) / "report.html"}


def _bench(work: Path) -> dict[str, Path]:
    rows = [BenchRow(f"XGBoost {trees} x {depth}", "xgboost", 50_000, 25_000, 0.02 * trees, 1e6 / trees,
                     6.0 + 10 / trees, 8.0 + 10 / trees) for trees, depth in ((50, 4), (200, 6), (800, 8))]
    curve = [CurvePoint("train rows", 1.0, n, 200, 0.1, 9.8, 9.1, 6.0 + 1e3 / n) for n in (1_000, 10_000, 50_000)]
    noise = [CurvePoint("noise", s, 50_000, 200, 0.1, 9.8 * s, 9.1 * s, 5.9 * s) for s in (0.5, 1.0, 2.0)]
    result = BenchResult(BenchPlan(), "engineered", "residual", rows, curve, noise,
                         OutOfRange((2.4, 3.0), 20_000, 10.0, 14.0, 10.0, 10.0, 0.2), 12.0)
    return {"bench": write_bench(result, work / "bench") / "report.html"}


def build_reports(work: Path) -> dict[str, Path]:
    """Every report kind the project writes as HTML, built small: report kind -> its report.html."""
    model = tiny_model(work / "model")
    return {**_batch(work, model), **_light(work, model), **_evaluation(work, model), **_tuning(work),
            **_table2(work), **_bench(work)}


@pytest.fixture(scope="module")
def reports(tmp_path_factory) -> dict[str, Path]:
    return build_reports(tmp_path_factory.mktemp("browser"))


# --- the checks -------------------------------------------------------------------------------------------


def test_batch__one_shared_plotly_bundle_linked_relatively(reports):
    batch = reports["batch"].parent.parent
    assert (batch / PLOTLY_JS).is_file()
    assert not list(batch.glob(f"*/{PLOTLY_JS}")), "no copy of plotly.js in a scan's folder"
    assert f'src="../{PLOTLY_JS}"' in reports["scan-full"].read_text()


def test_scan_reports__no_valid_or_no_corrected_pixel_said_in_words(reports):
    dark = reports["scan-no-valid-pixel"].read_text()
    assert "No valid pixel" in dark and not re.search(r"\bnan\b", dark.lower())
    # the maps of what was measured, no empty views and no 3-D view; never "no maps" beside the maps
    assert '<img src="maps.png"' in dark and "point_cloud.png" not in dark and PLOTLY_JS not in dark
    assert "no maps" not in dark
    flat = reports["scan-flat-wall"].read_text()
    assert "No pixel was corrected" in flat


def test_reports__every_kind_fits_a_1280_pixel_window_in_chromium(chromium, reports):
    seen = {kind: browse(chromium, page) for kind, page in reports.items()}  # one page per report kind
    for kind, findings in seen.items():
        width = findings["width"]
        assert findings["problems"] == [], (kind, findings["problems"])
        assert width <= WINDOW_PX and findings["scrollWidth"] <= WINDOW_PX, (kind, findings["scrollWidth"])
        for table in findings["tables"]:
            assert table["width"] <= width and table["right"] <= width + 1, (kind, table)
            assert not table["scrolls"], (kind, table)  # wrapped to fit, not hidden off to the side
        for image in findings["images"]:
            assert image["loaded"] and image["right"] <= width + 1, (kind, image)
        for plot in findings["plots"]:
            assert plot["svg"] and plot["right"] <= width + 1 and plot["height"] >= 400, (kind, plot)
        assert "nan" not in re.findall(r"[a-z]+", findings["text"].lower()), kind
    assert seen["scan-full"]["plots"] and seen["scan-full"]["images"], "the full report shows its figures"
    assert {image["src"] for image in seen["scan-no-valid-pixel"]["images"]} == {"maps.png", "thumbnail.png"}
    assert not seen["scan-no-valid-pixel"]["plots"]


def test_batch_summary__four_scans_one_unserved_fit_1280_by_800(chromium, reports, tmp_path):
    shot = tmp_path / "batch-summary.png"
    findings = browse(chromium, reports["batch"], screenshot=shot, height_px=800)
    assert findings["scrollWidth"] <= WINDOW_PX and findings["problems"] == [], findings["scrollWidth"]
    assert shot.is_file() and shot.stat().st_size > 0
    text = findings["text"]
    assert "4 scans in" in text and "1 unserved" in text
    rows = [line for line in text.splitlines() if line.split("\t")[0] in (LONG_NAME, "flat_wall", "dark",
                                                                         "wall_no_grid")]
    assert [row.split("\t")[0] for row in rows][:2] == ["wall_no_grid", "dark"] or \
        [row.split("\t")[0] for row in rows][:2] == ["dark", "wall_no_grid"], "problem rows first"
    assert all("⚠" in row for row in rows[:2])
    html = reports["batch"].read_text()
    assert "<details>" in html and "status-chart" in html and "Made by: model" in html
