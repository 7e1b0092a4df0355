"""What each pixel flag and each estimate of a corrected scan means: the one registry every output's legend is made of.

The LAS/LAZ JSON record (:func:`mpi_lidar.reporting.point_cloud_files.point_cloud_metadata`), the flag and estimate
tables of docs/reference/flags.md and docs/reference/point-clouds.md (:func:`doc_tables`, written between
``<!-- legend:NAME -->`` and ``<!-- /legend:NAME -->`` marks by ``python -m mpi_lidar.reporting.legend``; a test
checks the docs are up to date), the colours of the maps and the thumbnail, and the terminal's note codes all come
from here.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mpi_lidar.correction.options import INVALID_FLAGS, Estimate, Flag

# What a valid pixel the model leaves alone holds: the baseline (``--baseline``), never the raw depth as such.
BASELINE_DEPTH = "the baseline's: fused frequencies (default), measured with `--baseline raw`"


@dataclass(frozen=True)
class FlagLegend:
    """One flag's entry: its letter, what it means (short, for a file's record; long, for the docs), which depth a
    pixel so flagged holds, and its colour in maps and thumbnails."""

    letter: str
    short: str
    meaning: str
    depth: str
    colour: str


FLAG_LEGEND: dict[Flag, FlagLegend] = {
    Flag.CORRECTED: FlagLegend("C", "valid, corrected by the model", "valid, and the gate asked for correction",
                               "the model's", "#2e86de"),
    Flag.NOT_NEEDED: FlagLegend("N", "valid, skipped by a pixel-wise gate; baseline depth",
                                "valid, a pixel-wise gate (`consistency`) skipped it", BASELINE_DEPTH, "#c8d6e5"),
    Flag.NOT_FINITE: FlagLegend("F", "invalid: a NaN or infinite depth or amplitude",
                                "a NaN or infinite depth or amplitude", "NaN", "#222f3e"),
    Flag.NO_RETURN: FlagLegend("R", "invalid: no light above the noise",
                               "too little light at all frequencies together: their squared amplitudes over the "
                               "no-light noise (the read term of the scan's own noise law) summed below what no light "
                               "reaches as rarely as one frequency reaches 5 sigma (`min_amplitude_sigmas`); where a "
                               "surface past the combined ambiguity could give the amplitude, any one frequency below "
                               "5 sigma; or an amplitude of zero or less", "NaN", "#576574"),
    Flag.SATURATED: FlagLegend("S", "invalid: amplitude clipped (saturated)",
                               "an amplitude on the scan's own plateau of clipped amplitudes at some frequency, or "
                               "above `saturation_amplitude_v2` where a sensor profile or the options give it",
                               "NaN", "#ee5253"),
    Flag.INCONSISTENT: FlagLegend("I", "invalid: the frequencies' depths disagree",
                                  "the frequencies' unwrapped depths disagree beyond chi-square's 1 - 1e-6 quantile "
                                  "under the scan's own noise law (`inconsistent_p_value`): a wrong wrap count, a "
                                  "depth edge, a broken frequency", "NaN", "#ff9f43"),
    Flag.OUT_OF_RANGE: FlagLegend("O", "valid, outside the model's range; baseline depth",
                                  "valid and not gated out, but past the far end of the d_AS range the model was "
                                  "trained on, or more than `near_range_fraction` (15 %) nearer than its near end "
                                  "([../results/model-range.md](../results/model-range.md)); a pixel out of range "
                                  "that needs no correction is flagged by the gate instead", BASELINE_DEPTH,
                                  "#10ac84"),
    Flag.NO_MULTIPATH: FlagLegend("M", "valid, no facing surface causes multipath; baseline depth",
                                  "valid, but no surface of the scan faces it closely enough to cause "
                                  "`min_multipath_bias_m` (2 mm) of bias (geometry gate)", BASELINE_DEPTH, "#f6e58d"),
    Flag.UNCALIBRATED: FlagLegend("U", "valid, footprint estimate not significant; baseline depth",
                                  "valid, could hold multipath above the gate's threshold, but the scan's footprint "
                                  "estimate is not significant (`--footprint-area-m2 auto`)", BASELINE_DEPTH,
                                  "#a55eea"),
    Flag.AMBIGUOUS: FlagLegend("A", "wrap counts ambiguous; range as measured (wrapped)",
                               "the scan's depths are wrapped and the frequencies' wrap counts cannot be told apart "
                               "at the pixel's noise: the posterior probability of the best wrap counts is below "
                               "`min_unwrap_confidence` (0.999)",
                               "the measured highest-frequency depth, as measured (wrapped)", "#ff6b81"),
    Flag.BEYOND_AMBIGUITY: FlagLegend("B", "invalid: past the combined ambiguity distance",
                                      "the pixel's amplitude is far too weak for the range its phases give (below "
                                      "1 % of a white surface's there) and plausible one combined ambiguity farther "
                                      "(24.0 m for 12.5-31.25 MHz), where the amplitudes' unit is trusted; or its "
                                      "surface continues smoothly (depth and amplitude) from the far side of a wrap "
                                      "seam (neighbours at about 24 m and about 0 m) or from a region most of whose "
                                      "pixels the amplitude flags: the surface lies past it", "NaN", "#6c3483"),
    Flag.MIXED: FlagLegend("X", "invalid: mixed pixel at a depth edge (two surfaces)",
                           "the footprint straddles a depth edge: beside a jump of more than 5 cm, the frequencies' "
                           "depths or their amplitudes disagree beyond their noise, or the depth lies off the line "
                           "through two opposite neighbours, or between two flat sides (one or two pixels in from "
                           "each); its one depth lies between the surfaces (a flying pixel); no two-return fit the "
                           "data support", "NaN", "#48dbfb"),
    Flag.TWO_RETURNS: FlagLegend("T", "valid, mixed pixel resolved into two returns; the stronger one's depth",
                                 "a mixed pixel (as `mixed`) whose four equally spaced frequencies fit two returns "
                                 "within their noise, at least 2 m apart, the weaker holding at least 20 % of the "
                                 "light: the depth is the stronger return's, the weaker's range, share and 1-sigma are "
                                 "`second_return_depth`, `second_return_share` and `second_return_uncertainty` in "
                                 "corrected.zarr",
                                 "the stronger return's", "#1dd1a1"),
    Flag.BEYOND_PRIOR: FlagLegend("P", "valid, corrected beyond the training prior; the model's depth",
                                  "corrected by the model (as flag 0), but the equivalent rho_ABA or d_AB the scene "
                                  "geometry gives it lies beyond the largest the model was trained on: its "
                                  "uncertainty adds the share of the correction the prior leaves out",
                                  "the model's", "#e15f41"),
}

ESTIMATE_LEGEND: dict[Estimate, str] = {
    Estimate.NONE: "invalid (flags 2-5, 10 and 11): NaN",
    Estimate.MEASURED: "the highest frequency's depth (unwrapped): `--baseline raw`, frequencies that disagree, "
                       "flag 9, or a scan whose amplitude unit could not be measured; for flag 12 the stronger "
                       "return's range",
    Estimate.FUSED: "the frequencies' depths fused by inverse variance",
    Estimate.CORRECTED: "the model's (flags 0 and 13)",
}

FLAG_COLOURS = [FLAG_LEGEND[flag].colour for flag in Flag]


def flag_name(flag: Flag) -> str:
    """A flag's name as outputs write it: ``no_multipath``."""
    return flag.name.lower()


def flag_record() -> dict[str, dict[str, object]]:
    """The flags as a file's JSON record holds them: code -> name, letter, meaning, depth held, invalid."""
    return {str(int(flag)): {"name": flag_name(flag), "letter": entry.letter, "meaning": entry.short,
                             "depth": entry.depth.replace("`", ""), "invalid": flag in INVALID_FLAGS}
            for flag, entry in FLAG_LEGEND.items()}


def estimate_record() -> dict[str, str]:
    """The estimates as a file's JSON record holds them: name -> which pixels."""
    return {estimate.name.lower(): text.replace("`", "") for estimate, text in ESTIMATE_LEGEND.items()}


def _rows(headers: tuple[str, ...], rows: list[tuple[str, ...]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def doc_tables() -> dict[str, str]:
    """The markdown tables the docs hold, by the name of their marks: ``flags`` (docs/reference/flags.md),
    ``estimates`` (the same page) and ``point-cloud-flags`` (docs/reference/point-clouds.md)."""
    return {
        "flags": _rows(("code", "flag", "meaning", "output depth"),
                       [(str(int(f)), f"`{flag_name(f)}`", e.meaning, e.depth) for f, e in FLAG_LEGEND.items()]),
        "estimates": _rows(("code", "estimate", "which pixels"),
                           [(str(int(e)), f"`{e.name.lower()}`", text) for e, text in ESTIMATE_LEGEND.items()]),
        "point-cloud-flags": _rows(("code", "letter", "name", "meaning"),
                                   [(str(int(f)), e.letter, f"`{flag_name(f)}`",
                                     ("invalid (left out, or withheld): " + e.short.removeprefix("invalid: "))
                                     if f in INVALID_FLAGS else e.short) for f, e in FLAG_LEGEND.items()]),
    }


DOC_PAGES = ("docs/reference/flags.md", "docs/reference/point-clouds.md")


def _marked(name: str) -> re.Pattern[str]:
    return re.compile(rf"(<!-- legend:{re.escape(name)} -->\n).*?(\n<!-- /legend:{re.escape(name)} -->)", re.S)


def refreshed(text: str) -> str:
    """``text`` (a docs page) with every marked table replaced by the registry's."""
    for name, table in doc_tables().items():
        text = _marked(name).sub(_replacer(table), text)
    return text


def _replacer(table: str) -> Callable[[re.Match[str]], str]:
    def replace(marked: re.Match[str]) -> str:
        return marked.group(1) + table + marked.group(2)

    return replace


def main(root: str = ".") -> int:
    """Rewrite the marked tables of :data:`DOC_PAGES` under ``root``; prints the pages changed."""
    for page in DOC_PAGES:
        path = Path(root) / page
        old = path.read_text()
        new = refreshed(old)
        if new != old:
            path.write_text(new)
            print(f"updated {page}")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
