"""The report of one corrected scan: what was done per pixel, its errors, notes, outputs and figures."""

from __future__ import annotations

from pathlib import Path

from mpi_lidar.correction import INVALID_FLAGS, MODEL_FLAGS, Correction
from mpi_lidar.correction.corrected_store import footprint_record
from mpi_lidar.reporting.metrics import metrics_table
from mpi_lidar.reporting.output_levels import OutputLevel
from mpi_lidar.reporting.report import Block, Embed, Report, Table
from mpi_lidar.scans.scan import Scan

# What a report at each output level says the next level up would add.
_MORE = {
    OutputLevel.DATA: (" Level light adds this report, the LAZ point cloud and a thumbnail; full the maps, histogram "
                       "and PLY files."),
    OutputLevel.LIGHT: " Level full adds the maps, the error histogram, the point-cloud views and the PLY files.",
    OutputLevel.FULL: "",
}


def scan_report(scan: Scan, correction: Correction, metrics: dict[str, dict[str, float]], notes: list[str],
                figures: list[str], outputs: str = "full", files: list[str] | None = None,
                captions: dict[str, str] | None = None, embeds: list[Embed] | None = None) -> Report:
    """The scan's report: what was done per pixel, errors, notes, which outputs were written, the figures
    (each after its caption in ``captions``, if any) and then the ``embeds`` (the interactive 3-D view)."""
    counts = correction.counts()
    total = max(sum(counts.values()), 1)
    flags = Table(("pixels", "count", "share"),
                  tuple((name.replace("_", " "), f"{n:,}", f"{100 * n / total:.1f} %") for name, n in counts.items()))
    estimates = correction.estimate_counts()
    uncertainty = correction.uncertainty_summary()
    blocks: list[Block] = [f"Scan `{scan.name}`, {scan.shape[0]} x {scan.shape[1]} pixels at "
                           + ", ".join(f"{f / 1e6:g}" for f in scan.frequencies_hz) + " MHz. "
                           f"Correction {correction.total_s:.2f} s (gate {correction.gate_s:.2f} s, inference "
                           f"{correction.inference_s:.2f} s).", *_in_words(counts), flags]
    if estimates:
        blocks.append("Output depths: " + ", ".join(f"{name} {n:,}" for name, n in estimates.items() if n)
                      + (f"; 1-sigma uncertainty median {1e3 * uncertainty['median_m']:.3f} mm, 95 % below "
                         f"{1e3 * uncertainty['p95_m']:.3f} mm." if uncertainty else "."))
    if correction.unserved is not None:
        blocks.insert(1, f"Unserved ({correction.unserved.reason}): {correction.unserved.message}.")
    valid = _valid_pixels(counts)
    if valid and any(m.get("pixels") for m in metrics.values()):
        blocks.append(metrics_table(metrics))
    elif valid and metrics:
        blocks.append("No valid pixel has a reference depth: no errors to show.")
    files = sorted(files if files is not None else ["corrected.zarr", *figures, "metrics.json", "report.html",
                                                    "report.md"])
    more = _MORE[OutputLevel(outputs)]
    blocks += [*notes, f"Outputs (level {outputs}): {', '.join(files)}.{more}"]
    # The figures that were drawn (a scan without a valid pixel has its maps of what was measured and no views);
    # the 3-D view only where there are points.
    for name in figures:
        blocks += [captions[name]] if captions and name in captions else []
        blocks.append(Path(name))
    blocks += (embeds or []) if valid else []
    return Report(title=f"Correction of {scan.name}", blocks=blocks,
                  data={"scan": scan.name, "counts": counts, "estimates": correction.estimate_counts(),
                        "uncertainty": correction.uncertainty_summary(),
                        "frequency_offsets_m": correction.frequency_offsets_m,
                        "window_leakage_removed": correction.window_leakage_removed,
                        "metrics": metrics, "notes": notes,
                        "outputs": {"level": str(outputs), "files": files},
                        "seconds": {"total": correction.total_s, "gate": correction.gate_s,
                                    "inference": correction.inference_s},
                        **({} if correction.calibration is None else {"footprint": footprint_record(correction)}),
                        **({} if correction.unserved is None else {"unserved": correction.unserved.to_dict()})})


def _valid_pixels(counts: dict[str, int]) -> int:
    return sum(counts.values()) - sum(counts.get(flag.name.lower(), 0) for flag in INVALID_FLAGS)


def _named(counts: dict[str, int], flags: tuple[str, ...]) -> str:
    return ", ".join(f"{name.replace('_', ' ')} {counts[name]:,}" for name in flags if counts.get(name))


def _in_words(counts: dict[str, int]) -> list[str]:
    """A scan without a valid pixel, or without a corrected one, says so (instead of empty maps and NaN)."""
    invalid = tuple(flag.name.lower() for flag in INVALID_FLAGS)
    if not _valid_pixels(counts):
        return [f"**No valid pixel**: every pixel was flagged invalid ({_named(counts, invalid)}), so nothing was "
                "corrected and there are no errors or point clouds to show; the maps, where written, show what was "
                "measured. Check the scan's amplitudes (their unit and saturation) and depths."]
    model = tuple(flag.name.lower() for flag in MODEL_FLAGS)
    if not any(counts.get(name) for name in model):
        left = tuple(name for name in counts if name not in invalid and name not in model)
        return [f"**No pixel was corrected**: the model corrected none of the {_valid_pixels(counts):,} valid "
                f"pixels ({_named(counts, left)})."]
    return []
