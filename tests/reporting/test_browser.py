"""The HTML reports in a real headless browser: they render, raise no console error, and every image loads and
fits the page width. Chromium comes from the distribution, installed by `make system-deps`, never by a test."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from mpi_lidar.correction import CorrectionOptions
from mpi_lidar.reporting.batch_report import write_batch_report
from mpi_lidar.scans.store import write_scan
from mpi_lidar.workflows.correct_archive import correct_archive
from tests.model_factory import tiny_model
from tests.scan_factory import two_path_scan

PROBE = """<script>
window.__problems = [];
window.addEventListener("error", e => window.__problems.push("error: " + e.message), true);
const consoleError = console.error;
console.error = (...args) => { window.__problems.push("console: " + args.join(" ")); consoleError(...args); };
window.addEventListener("load", () => setTimeout(() => {
  const width = document.documentElement.clientWidth;
  const images = [...document.images].map(img => ({src: img.getAttribute("src"), loaded: img.complete &&
    img.naturalWidth > 0, right: img.getBoundingClientRect().right}));
  const out = document.createElement("pre");
  out.id = "probe";
  out.textContent = JSON.stringify({width, images, problems: window.__problems,
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


def browse(chromium: str, page: Path, tmp_path: Path) -> dict[str, object]:
    """Load a copy of ``page`` (beside its images) with the probe; the probe's findings and a screenshot."""
    probed = page.with_name(f".probed-{page.name}")
    probed.write_text(page.read_text().replace("<head>", "<head>" + PROBE, 1))
    flags = [chromium, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
             "--allow-file-access-from-files", "--window-size=1280,2000", "--virtual-time-budget=10000"]
    try:
        dom = subprocess.run([*flags, "--dump-dom", probed.as_uri()], capture_output=True, text=True, timeout=120)
        shot = tmp_path / f"{page.parent.name}.png"
        subprocess.run([*flags, f"--screenshot={shot}", probed.as_uri()], capture_output=True, timeout=120)
    finally:
        probed.unlink()
    match = re.search(r'<pre id="probe">(.*?)</pre>', dom.stdout, flags=re.S)
    assert match, f"the page did not finish loading: {dom.stderr[-2000:]}"
    findings = json.loads(match.group(1).replace("&quot;", '"').replace("&amp;", "&"))
    findings["screenshot_bytes"] = shot.stat().st_size if shot.exists() else 0
    return findings


@pytest.fixture(scope="module")
def reports(tmp_path_factory) -> list[Path]:
    work = tmp_path_factory.mktemp("browser")
    model = tiny_model(work / "model")
    write_scan(two_path_scan("frame", height=24, width=32), work / "scans" / "frame.scan.zarr")
    outcomes = correct_archive([str(work / "scans")], model, work / "out", CorrectionOptions(gate="all"),
                               outputs="full")
    assert [o.status for o in outcomes] == ["corrected"], outcomes
    write_batch_report(outcomes, 1.0, work / "out")
    return [work / "out" / "frame" / "report.html", work / "out" / "summary" / "report.html"]


@pytest.mark.slow
def test_reports__render_in_chromium_without_errors_and_images_fit(chromium, reports, tmp_path):
    for page in reports:
        findings = browse(chromium, page, tmp_path)
        assert findings["problems"] == [], (page, findings["problems"])
        assert findings["scrollWidth"] <= findings["width"] + 1, (page, findings)  # no horizontal overflow
        for image in findings["images"]:
            assert image["loaded"], (page, image)
            assert image["right"] <= findings["width"] + 1, (page, image)
        assert findings["screenshot_bytes"] > 10_000, page  # a rendered page, not a blank one
    assert browse(chromium, reports[0], tmp_path)["images"], "the scan report shows its figures"
