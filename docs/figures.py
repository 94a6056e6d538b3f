"""Every measured figure the README and the docs quote, read from its results file (issue 36).

A figure is a file under ``benchmarks/results/``, a key in it and a format. JSON keys are dotted
paths (``final.UCBC.wrms.0``: dictionary keys and list indices); CSV keys are
``column@key=value,key=value`` (the column of the one row whose other columns match).

* The docs site reads them at build time: ``docs/conf.py`` makes each a MyST substitution, so a
  page writes ``{{ wave_wrms_info }}`` and never types the number. A figure whose file is stale
  (``make results-status``) is shown with a visible "(measured on an older version)" note.
* The README, which GitHub and PyPI show as it is, writes each figure between markers,
  ``<!-- fig:NAME -->0.0496<!-- /fig -->``; ``tests/test_figures.py`` fails when the text between
  them differs from the file, when a page names a figure that is not here, or when a figure's key
  is not in its file.
* A whole table is a :class:`Table` (a file, its columns, which rows), written between a
  ``<!-- table:NAME -->`` line and a ``<!-- /table -->`` line; the same test holds it to its file.
* ``tests/test_prose_figures.py`` fails on a measured figure typed into a page outside a marker.
"""

from __future__ import annotations

import csv
import functools
import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
STALE_NOTE = " (measured on an older version)"
UNSTAMPED_NOTE = " (an older run, unstamped)"  # a file written before stamps: what code it ran is unknown


def dotted(value: Any, key: str) -> Any:
    """The value at the dotted path ``key`` inside ``value`` (dictionary keys and list indices). A
    dictionary key that itself holds dots (``"mixed, sigma_R = 0.1"``) is matched whole: at each
    level the longest run of the path's next parts that is a key is taken."""
    parts = [p for p in key.split(".") if p]
    i = 0
    while i < len(parts):
        if isinstance(value, list):
            value, i = value[int(parts[i])], i + 1
            continue
        for j in range(len(parts), i, -1):
            if ".".join(parts[i:j]) in value:
                value, i = value[".".join(parts[i:j])], j
                break
        else:
            raise KeyError(parts[i])
    return value


def load(file: str) -> Any:
    """A results file (under ``benchmarks/results/``) as parsed: a CSV's rows, or the JSON value. Read
    once per process while the file is unchanged (its modification time and size), since a page's
    figures read the same files many times; callers only read what it returns."""
    path = ROOT / "benchmarks" / "results" / file
    st = path.stat()
    return _parsed(path, st.st_mtime_ns, st.st_size)


@functools.cache
def _parsed(path: Path, mtime_ns: int, size: int) -> Any:
    if path.suffix == ".csv":
        with path.open(newline="") as fh:
            return list(csv.DictReader(fh))
    return json.loads(path.read_text())


@dataclass(frozen=True)
class Figure:
    file: str  # under benchmarks/results/
    key: str
    fmt: str = "{}"  # a str.format pattern, or one of "percent", "percent2", "kb_mb", "sci", "ms"

    def raw(self) -> float | int | str:
        if self.file.endswith(".csv"):
            column, _, where = self.key.partition("@")
            wanted = dict(kv.split("=", 1) for kv in where.split(",") if kv)
            rows = [r for r in load(self.file) if all(r.get(k) == v for k, v in wanted.items())]
            if len(rows) != 1:
                raise KeyError(f"{self.file}: {len(rows)} rows match {where!r}, expected 1")
            return float(rows[0][column])
        return dotted(load(self.file), self.key)

    def text(self) -> str:
        return formatted(self.raw(), self.fmt)


def formatted(value: object, fmt: str = "{}") -> str:
    """``value`` as a page shows it: ``fmt`` is a str.format pattern or one of the named formats."""
    if value is None:  # a measurement that found no such value (e.g. a size at which shards never pay)
        return "never"
    if fmt == "percent":
        return f"{100 * float(value):g} %"
    if fmt == "kb_mb":  # kilobytes shown in megabytes
        return f"{float(value) / 1000:.0f}"
    if fmt == "percent2":  # a share, to a tenth of a percent
        return f"{round(100 * float(value), 1):g} %"
    if fmt == "ms":  # seconds shown in milliseconds
        return f"{1000 * float(value):.1f} ms"
    if fmt == "sci":  # 4e-8 style, one significant digit
        mantissa, exponent = f"{float(value):.0e}".split("e")
        return f"{mantissa}e{int(exponent)}"
    return fmt.format(value)


def _rows(file: str, rows: str | Callable[[Any], list[dict]] = "") -> list[dict]:
    """The rows of a table's file: every row of a CSV, or the list (or ``{label: row}`` mapping, the label
    as ``__key__``) at the dotted path ``rows`` of a JSON file, or, where ``rows`` is a function, what it
    returns given the whole loaded JSON (rows the file holds only in a nested or per-cell form, such as
    counts of verdicts)."""
    value = load(file)
    if file.endswith(".csv"):
        return list(value)
    if callable(rows):
        return list(rows(value))
    value = dotted(value, rows)
    if isinstance(value, dict):
        return [{"__key__": k, **v} for k, v in value.items()]
    return list(value)


@dataclass(frozen=True)
class Table:
    """A whole markdown table read from one results file: ``columns`` are ``(header, key, fmt)``, a key
    a column of the CSV (or a dotted path inside each JSON row); ``where`` keeps the rows whose columns
    equal its values (as text), in the file's order. A page writes it between
    ``<!-- table:NAME -->`` and ``<!-- /table -->`` lines (``make pages`` fills it in).

    ``rows`` (JSON only) is the dotted path to the rows, or a function of the loaded JSON that returns
    them (a list of dictionaries, their values already what a cell shows or read by ``columns``):
    the way to a table the file holds in another shape, e.g. best-or-tied counts from a suite's
    per-cell verdicts (:func:`suite_counts`)."""

    file: str
    columns: tuple[tuple[str, str, str], ...]
    where: tuple[tuple[str, str], ...] = ()
    rows: str | Callable[[Any], list[dict]] = ""  # JSON: the dotted path to the rows, or a function of the file

    def raw_rows(self) -> list[dict]:
        found = [r for r in _rows(self.file, self.rows) if all(str(r.get(k)) == v for k, v in self.where)]
        if not found:
            raise KeyError(f"{self.file}: no rows match {dict(self.where)!r}")
        return found

    def text(self) -> str:
        def cell(row: dict, key: str, fmt: str) -> str:
            value = dotted(row, key)
            if isinstance(value, str) and fmt != "{}":
                value = float(value)
            return formatted(value, fmt)

        lines = ["| " + " | ".join(h for h, _, _ in self.columns) + " |"]
        lines.append("|" + "|".join("---" for _ in self.columns) + "|")
        for row in self.raw_rows():
            lines.append("| " + " | ".join(cell(row, k, f) for _, k, f in self.columns) + " |")
        return "\n".join(lines)


TABLES: dict[str, Table] = {}

_WAVE = "wave_summary.json"
_SPEED = "speed_quiet/speed_pairwise.csv"  # the quiet run of this round (stamped JSON beside it)
_PAIR = "paired_tests.queries.info per effort vs UCBC"

FIGURES: dict[str, Figure] = {
    # BoTorch parity (benchmarks/parity/botorch_api_counts.py)
    "api_checks_passed": Figure("botorch_api_counts.json", "summary.PreferenceGP.passed"),
    "api_checks_total": Figure("botorch_api_counts.json", "summary.PreferenceGP.total"),
    "api_checks_pairwisegp": Figure("botorch_api_counts.json", "summary.PairwiseGP.passed"),
    # speed against PairwiseGP and botorch-rust at n = 500 (benchmarks/speed/speed_pairwise.py)
    "speed_fit_500_pairwisegp": Figure(_SPEED, "ratio_pairwisegp@task=fit,n=500", "{:.1f}×"),
    "speed_fit_20_rust": Figure(_SPEED, "ratio_botorch_rust@task=fit,n=20", "{:.2f}×"),
    "speed_fit_50_rust": Figure(_SPEED, "ratio_botorch_rust@task=fit,n=50", "{:.1f}×"),
    "speed_mode_20_rust": Figure(_SPEED, "ratio_botorch_rust@task=mode,n=20", "{:.2f}×"),
    "speed_eubo_20_rust": Figure(_SPEED, "ratio_botorch_rust@task=eubo,n=20", "{:.2f}×"),
    "speed_fit_500_rust": Figure(_SPEED, "ratio_botorch_rust@task=fit,n=500", "{:.1f}×"),
    "speed_posterior_500_pairwisegp": Figure(_SPEED, "ratio_pairwisegp@task=posterior,n=500", "{:,.0f}×"),
    "speed_posterior_500_rust": Figure(_SPEED, "ratio_botorch_rust@task=posterior,n=500", "{:,.0f}×"),
    "speed_eubo_500_pairwisegp": Figure(_SPEED, "ratio_pairwisegp@task=eubo,n=500", "{:.1f}×"),
    "speed_eubo_500_rust": Figure(_SPEED, "ratio_botorch_rust@task=eubo,n=500", "{:.0f}×"),
    # the paper's Fig. 6 (torchpref reproduce wave)
    "wave_wrms_info": Figure(_WAVE, "final.info per effort.wrms.0", "{:.4f}"),
    "wave_wrms_ucbc": Figure(_WAVE, "final.UCBC.wrms.0", "{:.4f}"),
    "wave_tp_info": Figure(_WAVE, "final.info per effort.tp.0", "{:.2f}"),
    "wave_tp_ucbc": Figure(_WAVE, "final.UCBC.tp.0", "{:.2f}"),
    "wave_p_wrms": Figure(_WAVE, f"{_PAIR}.wrms.p_wilcoxon", "sci"),
    "wave_p_tp": Figure(_WAVE, f"{_PAIR}.tp.p_wilcoxon", "sci"),
    # lake monitoring, 10 lakes x 20 trials (torchpref reproduce lake)
    "lake_rated5_ucbc": Figure("lakes10_selector/lake_summary.json", "share_rated_5.UCBC", "percent"),
    "lake_rated5_clipped": Figure(
        "lakes10_selector_clipped/lake_summary.json", "share_rated_5.clipped profile", "percent"
    ),
    "lake_rated5_random": Figure("lakes10_selector/lake_summary.json", "share_rated_5.random ratings", "percent"),
    # real people's recorded choices replayed (torchpref reproduce replay)
    "replay_elec_info": Figure("replay/replay.json", "summary.electricity.information.accuracy.area", "{:.3f}"),
    "replay_elec_random": Figure("replay/replay.json", "summary.electricity.random.accuracy.area", "{:.3f}"),
    "replay_elec_info_p": Figure("replay/replay.json", "summary.electricity.information.accuracy.p", "{:.3f}"),
    # robustness (benchmarks/robustness/fuzz.py)
    "fuzz_problems": Figure("fuzz.json", "problems", "{:,}"),
    "fuzz_f64_exceptions": Figure("fuzz.json", "f64.exceptions"),
    "fuzz_f32_exceptions": Figure("fuzz.json", "f32.exceptions"),
    # Ax's loops: the documented config (tax.pairwise_gp_kernel's priors, outputscale <= 100) against
    # PairwiseGP, and torchpref's own priors against it
    "ax_pbo_box_seeds": Figure("ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.n_seeds", "{}"),
    "ax_pbo_box_cpu_ratio": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_box_fit_ratio": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.fit_cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_box_gen_ratio": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.gen_cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_box_cpu_pref": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_s_mean.cpu_s.PreferenceGP_pairwise_box",
        "{:.1f} s",
    ),
    "ax_pbo_box_cpu_pair": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_s_mean.cpu_s.PairwiseGP", "{:.1f} s"
    ),
    "ax_pbo_box_u_pref": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.utility_mean.PreferenceGP_pairwise_box",
        "{:.4f}",
    ),
    "ax_pbo_box_u_pair": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.utility_mean.PairwiseGP", "{:.4f}"
    ),
    "ax_pbo_box_wins": Figure("ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.wins_first", "{}"),
    "ax_pbo_box_ties": Figure("ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.ties", "{}"),
    "ax_pbo_box_p_t": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.paired_utility.t_p", "{:.2f}"
    ),
    "ax_pbo_box_p_worse": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.paired_utility.worse_one_sided_p", "{:.2f}"
    ),
    "ax_pbo_box_os": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.outputscale_median.PreferenceGP_pairwise_box",
        "{:.1f}",
    ),
    "ax_pbo_box_load_lo": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.load_average_range.0", "{:.1f}"
    ),
    "ax_pbo_box_load_hi": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.load_average_range.1", "{:.1f}"
    ),
    "ax_pbo_own_box_seeds": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.n_seeds", "{}"
    ),
    "ax_pbo_own_box_u_own": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.utility_mean.PreferenceGP", "{:.4f}"
    ),
    "ax_pbo_own_box_u_box": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.utility_mean.PreferenceGP_pairwise_box",
        "{:.4f}",
    ),
    "ax_pbo_own_box_wins": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.wins_first", "{}"
    ),
    "ax_pbo_own_box_p_t": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.paired_utility.t_p", "{:.2f}"
    ),
    "ax_pbo_own_box_p_worse": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.paired_utility.worse_one_sided_p",
        "{:.2f}",
    ),
    "ax_pbo_own_box_cpu_ratio": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_box_seeds": Figure("ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.n_seeds", "{}"),
    "ax_bope_box_cpu_ratio": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_box_fit_ratio": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.fit_cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_box_gen_ratio": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.gen_cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_box_cpu_pref": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_s_mean.cpu_s.PreferenceGP_pairwise_box",
        "{:.1f} s",
    ),
    "ax_bope_box_cpu_pair": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_s_mean.cpu_s.PairwiseGP", "{:.1f} s"
    ),
    "ax_bope_box_u_pref": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.utility_mean.PreferenceGP_pairwise_box",
        "{:.4f}",
    ),
    "ax_bope_box_u_pair": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.utility_mean.PairwiseGP", "{:.4f}"
    ),
    "ax_bope_box_wins": Figure("ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.wins_first", "{}"),
    "ax_bope_box_ties": Figure("ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.ties", "{}"),
    "ax_bope_box_p_t": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.paired_utility.t_p", "{:.2f}"
    ),
    "ax_bope_box_p_worse": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.paired_utility.worse_one_sided_p", "{:.2f}"
    ),
    "ax_bope_box_os": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.outputscale_median.PreferenceGP_pairwise_box",
        "{:.1f}",
    ),
    "ax_bope_box_load_lo": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.load_average_range.0", "{:.1f}"
    ),
    "ax_bope_box_load_hi": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.load_average_range.1", "{:.1f}"
    ),
    "ax_bope_own_box_seeds": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.n_seeds", "{}"
    ),
    "ax_bope_own_box_u_own": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.utility_mean.PreferenceGP", "{:.4f}"
    ),
    "ax_bope_own_box_u_box": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.utility_mean.PreferenceGP_pairwise_box",
        "{:.4f}",
    ),
    "ax_bope_own_box_wins": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.wins_first", "{}"
    ),
    "ax_bope_own_box_p_t": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.paired_utility.t_p", "{:.2f}"
    ),
    "ax_bope_own_box_p_worse": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.paired_utility.worse_one_sided_p",
        "{:.2f}",
    ),
    "ax_bope_own_box_cpu_ratio": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_box.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    # Ax's loops: the documented config and PairwiseGP in the same processes, on a quieter machine
    "ax_pbo_sp_seeds": Figure(
        "ax/pbo_same_process.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.n_seeds", "{}"
    ),
    "ax_pbo_sp_cpu_ratio": Figure(
        "ax/pbo_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_sp_fit_ratio": Figure(
        "ax/pbo_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.fit_cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_sp_gen_ratio": Figure(
        "ax/pbo_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.gen_cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_sp_cpu_pref": Figure(
        "ax/pbo_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_s_mean.cpu_s.PreferenceGP_pairwise_box",
        "{:.1f} s",
    ),
    "ax_pbo_sp_cpu_pair": Figure(
        "ax/pbo_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_s_mean.cpu_s.PairwiseGP",
        "{:.1f} s",
    ),
    "ax_pbo_sp_load_lo": Figure(
        "ax/pbo_same_process.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.load_average_range.0", "{:.1f}"
    ),
    "ax_pbo_sp_load_hi": Figure(
        "ax/pbo_same_process.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.load_average_range.1", "{:.1f}"
    ),
    "ax_bope_sp_seeds": Figure(
        "ax/bope_same_process.json", "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.n_seeds", "{}"
    ),
    "ax_bope_sp_cpu_ratio": Figure(
        "ax/bope_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_sp_fit_ratio": Figure(
        "ax/bope_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.fit_cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_sp_gen_ratio": Figure(
        "ax/bope_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_ratio_second_over_first.gen_cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_sp_cpu_pref": Figure(
        "ax/bope_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_s_mean.cpu_s.PreferenceGP_pairwise_box",
        "{:.1f} s",
    ),
    "ax_bope_sp_cpu_pair": Figure(
        "ax/bope_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.cpu_s_mean.cpu_s.PairwiseGP",
        "{:.1f} s",
    ),
    "ax_bope_sp_load_lo": Figure(
        "ax/bope_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.load_average_range.0",
        "{:.1f}",
    ),
    "ax_bope_sp_load_hi": Figure(
        "ax/bope_same_process.json",
        "comparisons.PreferenceGP_pairwise_box vs PairwiseGP.load_average_range.1",
        "{:.1f}",
    ),
    # Ax's loops: PreferenceGP with PairwiseGP's kernel priors against PairwiseGP
    "ax_pbo_pp_seeds": Figure("ax/pbo.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.n_seeds", "{}"),
    "ax_pbo_pp_cpu_ratio": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_pp_fit_ratio": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_ratio_second_over_first.fit_cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_pp_gen_ratio": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_ratio_second_over_first.gen_cpu_s",
        "{:.2f}×",
    ),
    "ax_pbo_pp_cpu_pref": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_s_mean.cpu_s.PreferenceGP_pairwise_priors",
        "{:.1f} s",
    ),
    "ax_pbo_pp_cpu_pair": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_s_mean.cpu_s.PairwiseGP", "{:.1f} s"
    ),
    "ax_pbo_pp_u_pref": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.utility_mean.PreferenceGP_pairwise_priors",
        "{:.4f}",
    ),
    "ax_pbo_pp_u_pair": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.utility_mean.PairwiseGP", "{:.4f}"
    ),
    "ax_pbo_pp_wins": Figure("ax/pbo.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.wins_first", "{}"),
    "ax_pbo_pp_ties": Figure("ax/pbo.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.ties", "{}"),
    "ax_pbo_pp_p_worse": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.paired_utility.worse_one_sided_p",
        "{:.2f}",
    ),
    "ax_pbo_pp_p_t": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.paired_utility.t_p", "{:.2f}"
    ),
    "ax_pbo_pp_load_lo": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.load_average_range.0", "{:.1f}"
    ),
    "ax_pbo_pp_load_hi": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.load_average_range.1", "{:.1f}"
    ),
    "ax_bope_pp_seeds": Figure("ax/bope.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.n_seeds", "{}"),
    "ax_bope_pp_cpu_ratio": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_pp_fit_ratio": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_ratio_second_over_first.fit_cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_pp_gen_ratio": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_ratio_second_over_first.gen_cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_pp_cpu_pref": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_s_mean.cpu_s.PreferenceGP_pairwise_priors",
        "{:.1f} s",
    ),
    "ax_bope_pp_cpu_pair": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.cpu_s_mean.cpu_s.PairwiseGP", "{:.1f} s"
    ),
    "ax_bope_pp_u_pref": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.utility_mean.PreferenceGP_pairwise_priors",
        "{:.4f}",
    ),
    "ax_bope_pp_u_pair": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.utility_mean.PairwiseGP", "{:.4f}"
    ),
    "ax_bope_pp_wins": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.wins_first", "{}"
    ),
    "ax_bope_pp_ties": Figure("ax/bope.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.ties", "{}"),
    "ax_bope_pp_p_worse": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.paired_utility.worse_one_sided_p",
        "{:.2f}",
    ),
    "ax_bope_pp_p_t": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.paired_utility.t_p", "{:.2f}"
    ),
    "ax_bope_pp_load_lo": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.load_average_range.0", "{:.1f}"
    ),
    "ax_bope_pp_load_hi": Figure(
        "ax/bope.json", "comparisons.PreferenceGP_pairwise_priors vs PairwiseGP.load_average_range.1", "{:.1f}"
    ),
    # Ax's PBO and BOPE loops, PreferenceGP against PairwiseGP and against PairwiseGP's priors
    # (benchmarks/parity/ax_loops.py, issue 32)
    "ax_pbo_seeds": Figure("ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.n_seeds", "{}"),
    "ax_pbo_cpu_ratio": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_ratio_second_over_first.cpu_s", "{:.2f}×"
    ),
    "ax_pbo_fit_ratio": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_ratio_second_over_first.fit_cpu_s", "{:.2f}×"
    ),
    "ax_pbo_gen_ratio": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_ratio_second_over_first.gen_cpu_s", "{:.2f}×"
    ),
    "ax_pbo_cpu_pref": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_s_mean.cpu_s.PreferenceGP", "{:.1f} s"
    ),
    "ax_pbo_cpu_pair": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_s_mean.cpu_s.PairwiseGP", "{:.1f} s"
    ),
    "ax_pbo_u_pref": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.utility_mean.PreferenceGP", "{:.4f}"
    ),
    "ax_pbo_u_pair": Figure("ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.utility_mean.PairwiseGP", "{:.4f}"),
    "ax_pbo_wins": Figure("ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.wins_first", "{}"),
    "ax_pbo_p_worse": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.paired_utility.worse_one_sided_p", "{:.2f}"
    ),
    "ax_pbo_p_t": Figure("ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.paired_utility.t_p", "{:.2f}"),
    "ax_pbo_os_pref": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.outputscale_median.PreferenceGP", "{:.1f}"
    ),
    "ax_pbo_os_pair": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.outputscale_median.PairwiseGP", "{:.1f}"
    ),
    "ax_pbo_load_lo": Figure("ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.load_average_range.0", "{:.1f}"),
    "ax_pbo_load_hi": Figure("ax/pbo.json", "comparisons.PreferenceGP vs PairwiseGP.load_average_range.1", "{:.1f}"),
    "ax_pbo_prior_seeds": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.n_seeds", "{}"
    ),
    "ax_pbo_prior_u": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.utility_mean.PreferenceGP_pairwise_priors",
        "{:.4f}",
    ),
    "ax_pbo_prior_u_pref": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.utility_mean.PreferenceGP", "{:.4f}"
    ),
    "ax_pbo_prior_wins": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.wins_first", "{}"
    ),
    "ax_pbo_prior_ties": Figure("ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.ties", "{}"),
    "ax_pbo_prior_p_t": Figure(
        "ax/pbo.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.paired_utility.t_p", "{:.2f}"
    ),
    "ax_pbo_prior_os": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.outputscale_median.PreferenceGP_pairwise_priors",
        "{:.1f}",
    ),
    "ax_pbo_prior_cpu_ratio": Figure(
        "ax/pbo.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
    "ax_bope_seeds": Figure("ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.n_seeds", "{}"),
    "ax_bope_cpu_ratio": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_ratio_second_over_first.cpu_s", "{:.2f}×"
    ),
    "ax_bope_fit_ratio": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_ratio_second_over_first.fit_cpu_s", "{:.2f}×"
    ),
    "ax_bope_gen_ratio": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_ratio_second_over_first.gen_cpu_s", "{:.2f}×"
    ),
    "ax_bope_cpu_pref": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_s_mean.cpu_s.PreferenceGP", "{:.1f} s"
    ),
    "ax_bope_cpu_pair": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.cpu_s_mean.cpu_s.PairwiseGP", "{:.1f} s"
    ),
    "ax_bope_u_pref": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.utility_mean.PreferenceGP", "{:.4f}"
    ),
    "ax_bope_u_pair": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.utility_mean.PairwiseGP", "{:.4f}"
    ),
    "ax_bope_wins": Figure("ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.wins_first", "{}"),
    "ax_bope_p_worse": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.paired_utility.worse_one_sided_p", "{:.2f}"
    ),
    "ax_bope_p_t": Figure("ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.paired_utility.t_p", "{:.2f}"),
    "ax_bope_os_pref": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.outputscale_median.PreferenceGP", "{:.1f}"
    ),
    "ax_bope_os_pair": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.outputscale_median.PairwiseGP", "{:.1f}"
    ),
    "ax_bope_load_lo": Figure("ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.load_average_range.0", "{:.1f}"),
    "ax_bope_load_hi": Figure("ax/bope.json", "comparisons.PreferenceGP vs PairwiseGP.load_average_range.1", "{:.1f}"),
    "ax_bope_prior_seeds": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.n_seeds", "{}"
    ),
    "ax_bope_prior_u": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.utility_mean.PreferenceGP_pairwise_priors",
        "{:.4f}",
    ),
    "ax_bope_prior_u_pref": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.utility_mean.PreferenceGP", "{:.4f}"
    ),
    "ax_bope_prior_wins": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.wins_first", "{}"
    ),
    "ax_bope_prior_ties": Figure("ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.ties", "{}"),
    "ax_bope_prior_p_t": Figure(
        "ax/bope.json", "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.paired_utility.t_p", "{:.2f}"
    ),
    "ax_bope_prior_os": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.outputscale_median.PreferenceGP_pairwise_priors",
        "{:.1f}",
    ),
    "ax_bope_prior_cpu_ratio": Figure(
        "ax/bope.json",
        "comparisons.PreferenceGP vs PreferenceGP_pairwise_priors.cpu_ratio_second_over_first.cpu_s",
        "{:.2f}×",
    ),
}

# a population prior on real people, leave-people-out (benchmarks/studies/population.py), and its scale
for _ds, _short in (("electricity", "elec"), ("rail", "rail")):
    for _k in (0, 1, 2, 4, 8):
        _at = f"summary.{_ds}.{_k}"
        for _m, _mm in (("population", "pop"), ("own GP", "own"), ("pooled", "pooled")):
            FIGURES[f"popul_{_short}_{_mm}_k{_k}"] = Figure(
                "population/population.json", f"{_at}.{_m}.accuracy", "{:.3f}"
            )
        for _b, _bb in (("own GP", "own"), ("pooled", "pooled")):
            FIGURES[f"popul_{_short}_p_{_bb}_k{_k}"] = Figure(
                "population/population.json", f"{_at}.vs {_b}.p", "{:.2g}"
            )
    FIGURES[f"popul_{_short}_people"] = Figure("population/population.json", f"summary.{_ds}.0.people")
FIGURES["popul_scale_wall"] = Figure("population/population_scale.json", "fit_wall_seconds", "{:.0f}")
FIGURES["popul_scale_cpu"] = Figure("population/population_scale.json", "fit_cpu_seconds", "{:.0f}")
FIGURES["popul_scale_answers"] = Figure("population/population_scale.json", "answers", "{:,}")
FIGURES["popul_scale_proc_wall"] = Figure("population/population_scale_processes.json", "fit_wall_seconds", "{:.0f}")
FIGURES["popul_scale_spearman"] = Figure("population/population_scale.json", "spearman_mean_vs_truth", "{:.3f}")
FIGURES["popul_scale_load"] = Figure("population/population_scale.json", "load_average_start.0", "{:.1f}")
# issue 47: the mean at inducing items on real people, 10,000 people with their own items, shards that pay
for _ds, _short in (("electricity", "elec"), ("rail", "rail")):
    for _k in (0, 1, 2, 4, 8):
        _at = f"summary.{_ds}.{_k}"
        FIGURES[f"popul_{_short}_ind_k{_k}"] = Figure(
            "population/population.json", f"{_at}.population, inducing.accuracy", "{:.3f}"
        )
        FIGURES[f"popul_{_short}_gap_k{_k}"] = Figure(
            "population/population.json", f"{_at}.vs population, inducing.diff", "{:+.4f}"
        )
    FIGURES[f"popul_{_short}_ind_M"] = Figure(
        "population/population.json", f"fits.{_ds}.0.population, inducing.inducing_items"
    )
    FIGURES[f"popul_{_short}_N"] = Figure("population/population.json", f"fits.{_ds}.0.population.items", "{:,}")
    FIGURES[f"popul_{_short}_train"] = Figure("population/population.json", f"fits.{_ds}.0.train_people")
_OWN = "population/population_scale_own10k.json"
for _name, _key, _fmt in (
    ("people", "config.people", "{:,}"),
    ("items", "distinct_items", "{:,}"),
    ("answers", "answers", "{:,}"),
    ("M", "inducing_items", "{}"),
    ("wall", "fit_wall_seconds", "{:.0f}"),
    ("cpu", "fit_cpu_seconds", "{:.0f}"),
    ("load", "load_average_start.0", "{:.1f}"),
    ("peak", "peak_memory_gb.master", "{:.2f}"),
    ("before", "peak_memory_before_fit_gb", "{:.2f}"),
    ("estimate", "memory_estimate_gb", "{:.2f}"),
    ("spearman", "spearman_mean_vs_truth", "{:.4f}"),
):
    FIGURES[f"popul_own_{_name}"] = Figure(_OWN, _key, _fmt)
_SHARDS = "population/population_shards.json"
for _i, _people in enumerate((1000, 5000, 20000)):
    FIGURES[f"popul_shards_{_people}_local"] = Figure(_SHARDS, f"rows.{2 * _i}.s_per_evaluation", "{:.2f}")
    FIGURES[f"popul_shards_{_people}_dask"] = Figure(_SHARDS, f"rows.{2 * _i + 1}.s_per_evaluation", "{:.2f}")
    FIGURES[f"popul_shards_{_people}_bytes"] = Figure(_SHARDS, f"rows.{2 * _i + 1}.bytes_per_newton_step", "{:,}")
FIGURES["popul_shards_eff"] = Figure(_SHARDS, "model.efficiency", "{:.2f}")
for _k in (2, 4, 8, 16):
    FIGURES[f"popul_shards_pays_k{_k}"] = Figure(_SHARDS, f"model.pays_from_people.{_k}", "{:,}")

# twins of real people and the default's choice (issue 41; docs/selection.md): benchmarks/studies/twins.py,
# the population replay (torchpref reproduce replay --population) and benchmarks/studies/select_default.py
_TWINS_SEL = {
    "random": "random mixed", "rankings": "random rankings", "ucbc": "UCBC", "info": "utility info",
    "clipped": "clipped profile", "comb": "combination", "qeubo": "qEUBO", "sum": "information + profile",
}  # fmt: skip
for _ds, _dd in (("electricity", "elec"), ("rail", "rail")):
    for _c, _cc in (("no population", "nopop"), ("population", "pop")):
        _at = f"summary.plain.cells.{_ds}/{_c}.strategies"
        FIGURES[f"twins_{_dd}_{_cc}_random_final"] = Figure(
            "twins/twins.json", f"{_at}.random mixed.reach.baseline_final", "{:.3f}"
        )
        for _ss, _s in _TWINS_SEL.items():
            _t = f"twins_{_dd}_{_cc}_{_ss}"
            FIGURES[f"{_t}_area"] = Figure("twins/twins.json", f"{_at}.{_s}.concordance.area", "{:.3f}")
            if _ss != "random":
                FIGURES[f"{_t}_diff"] = Figure("twins/twins.json", f"{_at}.{_s}.concordance.mean_diff", "{:+.3f}")
                FIGURES[f"{_t}_p"] = Figure("twins/twins.json", f"{_at}.{_s}.concordance.p_wilcoxon", "{:.2g}")
                FIGURES[f"{_t}_reach"] = Figure("twins/twins.json", f"{_at}.{_s}.reach.median", "{:g}")
                FIGURES[f"{_t}_curve"] = Figure("twins/twins.json", f"{_at}.{_s}.reach.mean_curve", "{}")
_CANDIDATES = ("ucbc", "info", "clipped", "comb", "qeubo", "sum")
for _e in ("plain", "trajectories"):
    for _ss, _s in _TWINS_SEL.items():
        FIGURES[f"twins_{_e}_bot_{_ss}"] = Figure("twins/twins.json", f"summary.{_e}.best_or_tied.{_s}.0")
        if _ss in _CANDIDATES:
            FIGURES[f"fam_{_e}_{_ss}"] = Figure(
                f"select41_{_e}/merged_summary.json", f"equal_seconds_best_or_tied.{_s}.0"
            )
FIGURES["twins_plain_cells"] = Figure("twins/twins.json", "summary.plain.best_or_tied.random mixed.1")
_REPLAY_SEL = {
    "ucbc": "UCBC", "info": "information", "clipped": "clipped profile", "comb": "combination", "qeubo": "qEUBO",
    "sum": "information + profile",
}  # fmt: skip
for _ds, _dd in (("electricity", "elec"), ("rail", "rail")):
    _at = f"summary.{_ds}"
    FIGURES[f"replaypop_{_dd}_random_acc"] = Figure(
        "replay_population/replay.json", f"{_at}.random.accuracy.area", "{:.3f}"
    )
    FIGURES[f"replaypop_{_dd}_pairs"] = Figure("replay_population/replay.json", f"{_at}.random.pairs")
    for _ss, _s in _REPLAY_SEL.items():
        for _m, _mm in (("accuracy", "acc"), ("log_loss", "loss"), ("top1", "top1")):
            _f = f"replaypop_{_dd}_{_ss}_{_mm}"
            FIGURES[f"{_f}_diff"] = Figure("replay_population/replay.json", f"{_at}.{_s}.{_m}.diff", "{:+.3f}")
            FIGURES[f"{_f}_p"] = Figure("replay_population/replay.json", f"{_at}.{_s}.{_m}.p", "{:.2g}")
# the decision's table (benchmarks/studies/select_default.py decide), once default_choice.json exists
if (ROOT / "benchmarks" / "results" / "default_choice.json").is_file():
    for _ss, _s in _TWINS_SEL.items():
        if _ss in _CANDIDATES:
            FIGURES[f"choice_{_ss}_met"] = Figure("default_choice.json", f"candidates.{_s}.criteria_met")
            FIGURES[f"choice_{_ss}_ideal_worse"] = Figure(
                "default_choice.json", f"candidates.{_s}.idealised_worse_total"
            )
    FIGURES["choice_criteria"] = Figure("default_choice.json", "candidates.UCBC.criteria")
FIGURES["replay_rail_random"] = Figure("replay/replay.json", "summary.rail.random.accuracy.area", "{:.3f}")

# the quiet speed run's table (docs/speed.md): each task and size against each peer
for _task in ("mode", "fit", "posterior", "eubo"):
    for _n in (20, 50, 100, 200, 500):
        for _col, _peer in (("ratio_pairwisegp", "pgp"), ("ratio_botorch_rust", "rust")):
            FIGURES[f"speedq_{_task}_{_n}_{_peer}"] = Figure(_SPEED, f"{_col}@task={_task},n={_n}", "{:,.2f}×")

# the fuzz's run time and its per-precision times (docs/precision.md, docs/decisions.md)
FIGURES["fuzz_seconds"] = Figure("fuzz.json", "seconds", "{:.0f}")
FIGURES["fuzz_load"] = Figure("fuzz.json", "stamp.load_avg.0", "{:.1f}")
for _group, _g in (("all", "all"), ("n < 100", "small"), ("100 <= n < 500", "mid"), ("n >= 500", "large")):
    for _col in ("f64", "f32", "f32n", "f32_over_f32n", "f32_over_f64"):
        FIGURES[f"fuzz_s_{_g}_{_col}"] = Figure("fuzz.json", f"seconds_per_run.{_group}.{_col}", "{:.3g}")
    FIGURES[f"fuzz_s_{_g}_problems"] = Figure("fuzz.json", f"seconds_per_run.{_group}.problems", "{:,}")

# the serve soak (docs/serve.md)
FIGURES["soak_finished_kb"] = Figure("serve/soak.json", "summary.finished_session_kb_slope", "{:.0f}")
FIGURES["soak_finished_kb_half"] = Figure("serve/soak.json", "summary.finished_session_kb_slope_second_half", "{:.0f}")
FIGURES["soak_open_kb"] = Figure("serve/soak.json", "restart.open_session_kb_slope", "{:.0f}")
FIGURES["soak_files_max"] = Figure("serve/soak.json", "summary.session_files_max_in_run")
FIGURES["soak_worker_mb"] = Figure("serve/soak.json", "summary.worker_rss_kb_max", "kb_mb")
FIGURES["replay_seconds"] = Figure("replay/replay.json", "meta.seconds", "{:.1f}")
FIGURES["replay_load"] = Figure("replay/replay.json", "meta.load_average_start_end.0", "{:.1f}")
for _i, _q in enumerate(("p50", "p95", "p99")):
    FIGURES[f"soak_ms_{_q}"] = Figure("serve/soak.json", f"summary.answer_ms_p50_p95_p99.{_i}", "{:.0f}")
    FIGURES[f"soak_plots_ms_{_q}"] = Figure(
        "serve/soak.json", f"summary.answer_ms_during_plots_p50_p95_p99_n.{_i}", "{:.0f}"
    )
FIGURES["soak_lost"] = Figure("serve/soak.json", "restart.lost_answers")
FIGURES["soak_acknowledged"] = Figure("serve/soak.json", "restart.acknowledged_answers", "{:,}")
FIGURES["soak_reopened"] = Figure("serve/soak.json", "restart.sessions_reopened")
FIGURES["soak_load_lo"] = Figure("serve/soak.json", "load_average.0", "{:.1f}")
FIGURES["soak_load_hi"] = Figure("serve/soak.json", "load_average.3", "{:.1f}")
FIGURES["soak_per_hour"] = Figure("serve/soak.json", "summary.sessions_per_hour_in_run", "{:,.0f}")
FIGURES["soak_cpu_ms"] = Figure("serve/soak.json", "summary.server_cpu_s_per_answer", "ms")
FIGURES["soak_per_hour_cpu"] = Figure("serve/soak.json", "summary.participants_per_hour_cpu_bound", "{:,.0f}")

# real people who rate and rank (torchpref reproduce sushi; docs/real_raters.md)
_SUSHI, _RATING_MODEL = "sushi/sushi.json", "sushi/rating_model.json"
FIGURES["sushi_seconds"] = Figure(_SUSHI, "meta.seconds", "{:,.0f}")
FIGURES["sushi_load"] = Figure(_SUSHI, "meta.load_average_start_end.0", "{:.1f}")
FIGURES["sushi_people"] = Figure(_SUSHI, "meta.people")
FIGURES["sushi_seeds"] = Figure(_SUSHI, "meta.seeds")
FIGURES["sushi_train"] = Figure(_SUSHI, "meta.population_people")
FIGURES["sushi_calib_people"] = Figure(_RATING_MODEL, "people")
_REFS = (("r", "all ratings"), ("k", "the ranking"), ("b", "both"))
_TGT = (("rank", "ranking"), ("rate", "ratings"))
for _i, _nu in enumerate((1, 2, 3, 5, 10, 20, 80)):
    FIGURES[f"sushi_nu{_nu}_ev"] = Figure(_RATING_MODEL, f"rows.{_i}.evidence_both", "{:,.0f}")
    for _r, _ref in _REFS:
        for _t, _target in _TGT:
            FIGURES[f"sushi_nu{_nu}_{_r}_{_t}"] = Figure(_RATING_MODEL, f"rows.{_i}.{_ref}:{_target}", "{:.3f}")
for _c in ("none", "population"):
    _C = f"summary.conditions.{_c}"
    for _r, _ref in _REFS:
        for _t, _target in _TGT:
            FIGURES[f"sushi_{_c}_ref_{_r}_{_t}"] = Figure(_SUSHI, f"{_C}.references.{_ref}.{_target}", "{:.3f}")
    for _key, _name in (
        ("b_r_rank", "both_vs_ratings_on_ranking"),
        ("b_k_rate", "both_vs_ranking_on_ratings"),
        ("b_k_rank", "both_vs_ranking_on_ranking"),
        ("b_r_rate", "both_vs_ratings_on_ratings"),
    ):
        FIGURES[f"sushi_{_c}_p_{_key}"] = Figure(_SUSHI, f"{_C}.tests.{_name}.p_wilcoxon", "{:.2g}")
        FIGURES[f"sushi_{_c}_d_{_key}"] = Figure(_SUSHI, f"{_C}.tests.{_name}.mean_diff", "{:+.3f}")
    FIGURES[f"sushi_{_c}_default_ratings"] = Figure(_SUSHI, f"{_C}.policies.default.rating_share_first6", "percent2")
    for _k in range(5):
        _T = f"{_C}.tests.default_vs_best_single_kind.ranking.{_k}"
        FIGURES[f"sushi_{_c}_best_{_k}"] = Figure(_SUSHI, f"{_T}.best_single_kind")
        FIGURES[f"sushi_{_c}_diff_{_k}"] = Figure(_SUSHI, f"{_T}.mean_diff", "{:+.3f}")
        FIGURES[f"sushi_{_c}_pd_{_k}"] = Figure(_SUSHI, f"{_T}.p_wilcoxon", "{:.2g}")
    for _k in range(5):
        _T = f"{_C}.tests.default_vs_best_single_kind.ratings.{_k}"
        FIGURES[f"sushi_{_c}_rbest_{_k}"] = Figure(_SUSHI, f"{_T}.best_single_kind")
        FIGURES[f"sushi_{_c}_rdiff_{_k}"] = Figure(_SUSHI, f"{_T}.mean_diff", "{:+.3f}")
        FIGURES[f"sushi_{_c}_rpd_{_k}"] = Figure(_SUSHI, f"{_T}.p_wilcoxon", "{:.2g}")
    for _k, _b in enumerate(("6.8", "27.2")):
        FIGURES[f"sushi_{_c}_default_at_{_k}"] = Figure(
            _SUSHI, f"{_C}.policies.default.ranking.by_seconds.{4 * _k}", "{:.3f}"
        )

# the study on twins and the study over HTTP (docs/study.md)
for _ds, _short in (("electricity", "elec"), ("rail", "rail")):
    for _k in (0, 2, 5, 10):
        for _c in ("online", "none"):
            FIGURES[f"study_{_short}_k{_k}_{_c}"] = Figure(
                "study/study_twins.json", f"summary.{_ds}.{_k}.after_20.{_c}", "{:.3f}"
            )
        FIGURES[f"study_{_short}_k{_k}_p"] = Figure(
            "study/study_twins.json", f"summary.{_ds}.{_k}.after_20.p", "{:.1g}"
        )
    FIGURES[f"study_{_short}_pairs"] = Figure("study/study_twins.json", f"summary.{_ds}.2.after_20.pairs")
for _i, (_ds, _n) in enumerate((("elec", 10), ("elec", 50), ("elec", 200), ("rail", 10), ("rail", 50), ("rail", 200))):
    for _w in ("cold", "warm"):
        FIGURES[f"study_refit_{_ds}_{_n}_{_w}"] = Figure("study/study_twins.json", f"refit_cost.{_i}.{_w}_s", "{:.1f}")
FIGURES["study_twins_load_lo"] = Figure("study/study_twins.json", "meta.load_average_start_end.1", "{:.0f}")
FIGURES["study_twins_load_hi"] = Figure("study/study_twins.json", "meta.load_average_start_end.0", "{:.0f}")
for _key in (
    "participants",
    "acknowledged",
    "kills",
    "kills_during_refit",
    "finished",
    "refits",
    "export_rows",
    "answer_records_in_files",
    "report_figures_shown_in_chromium",
    "seconds",
):
    FIGURES[f"study_run_{_key}"] = Figure("study/study_run.json", _key, "{:,}")
FIGURES["study_run_per5"] = Figure("study/study_run.json", "refits_per_5_finished", "{:.2f}")
FIGURES["study_run_load"] = Figure("study/study_run.json", "load_average_start_end.1", "{:.1f}")
for _key in (
    "acknowledged",
    "kills",
    "kills_during_refit",
    "export_rows",
    "answer_records_in_files",
    "refits",
    "finished",
):
    FIGURES[f"study_kill_{_key}"] = Figure("study/study_run_kills.json", _key, "{:,}")
FIGURES["study_kill_lost"] = Figure("study/study_run_kills.json", "lost", "{}")
FIGURES["study_kill_load"] = Figure("study/study_run_kills.json", "load_average_start_end.1", "{:.1f}")

# the compiled fit's line search across problems (benchmarks/speed/speed_line_search.py; issue 52)
_LS = "line_search/speed_line_search.json"
FIGURES["ls_fits"] = Figure(_LS, "summary.fits")
FIGURES["ls_fallbacks"] = Figure(_LS, "summary.fallbacks")
FIGURES["ls_max_evaluations"] = Figure(_LS, "summary.max_evaluations")
FIGURES["ls_load_start"] = Figure(_LS, "summary.load_avg_start.0", "{:.1f}")

# the compiled path's threads and person models (benchmarks/speed/speed_fast_path.py, make results; issue 42)
_FAST = "fast_path/speed_fast_path.json"
for _i, _n in enumerate((20, 50, 100, 200)):
    for _key in ("quiet_limited_cpu_s", "quiet_unlimited_cpu_s", "loaded_limited_cpu_s"):
        FIGURES[f"fast_{_key.removesuffix('_cpu_s')}_{_n}"] = Figure(_FAST, f"load.{_i}.{_key}", "ms")
    for _key in (
        "limited_loaded_over_quiet_cpu",
        "unlimited_loaded_over_quiet_cpu",
        "quiet_unlimited_cpu_over_wall_max",
        "loaded_limited_cpu_over_wall_max",
    ):
        FIGURES[f"fast_{_key}_{_n}"] = Figure(_FAST, f"load.{_i}.{_key}", "{:.2f}")
    for _j, _task in enumerate(("fit", "solve")):
        FIGURES[f"fast_person_{_task}_{_n}"] = Figure(_FAST, f"person.{2 * _i + _j}.speedup_cpu", "{:.1f}×")
        for _side in ("compiled", "torch"):
            FIGURES[f"fast_person_{_task}_{_n}_{_side}"] = Figure(_FAST, f"person.{2 * _i + _j}.{_side}_cpu_s", "ms")
FIGURES["fast_load_start"] = Figure(_FAST, "meta.load_average_at_start.0", "{:.1f}")

# large pools: the shortlist's accuracy and the cost of a question (benchmarks/speed/large_pools.py)
_LP_ACC, _LP_COST = "large_pools/accuracy.json", "large_pools/cost.csv"
FIGURES["large_pool_acc_runs"] = Figure(_LP_ACC, "by_N.2000.runs")
for _n in (500, 1000, 2000):
    FIGURES[f"large_pool_acc_{_n}"] = Figure(_LP_ACC, f"by_N.{_n}.mean_given_up", "{:+.1%}")
    FIGURES[f"large_pool_acc_{_n}_noise"] = Figure(_LP_ACC, f"by_N.{_n}.mean_other_seed_given_up", "{:+.1%}")
    FIGURES[f"large_pool_acc_{_n}_same"] = Figure(_LP_ACC, f"by_N.{_n}.same_share", "{:.0%}")
FIGURES["large_pool_load"] = Figure("large_pools/cost.json", "load_at_start.0", "{:.1f}")
for _name, _where in (
    ("100k", "N=100000,d=4,method=session"),
    ("100k_d16", "N=100000,d=16,method=session"),
    ("1m", "N=1000000,d=4,method=session"),
    ("1m_d16", "N=1000000,d=16,method=session"),
    ("exact_3000", "N=3000,d=4,method=exact"),
    ("qeubo_100k", "N=100000,d=4,method=botorch_qeubo"),
):
    FIGURES[f"large_pool_{_name}_cpu"] = Figure(_LP_COST, f"cpu_s@{_where}", "{:.2f} s")
    FIGURES[f"large_pool_{_name}_mem"] = Figure(_LP_COST, f"peak_rss_mb@{_where}", "{:,.0f} MB")

_LP_SERVE = "large_pools/serve.csv"
for _col in ("read_csv_s", "new_participant_s", "answer_median_s", "summary_s", "utility_png_s"):
    FIGURES[f"large_pool_serve_{_col.removesuffix('_s')}"] = Figure(_LP_SERVE, f"{_col}@N=100000", "{:.2f} s")
FIGURES["large_pool_serve_file_kb"] = Figure(_LP_SERVE, "session_file_kb@N=100000", "{:.0f} kB")
FIGURES["large_pool_serve_load"] = Figure("large_pools/serve.json", "load_at_start.0", "{:.1f}")

# --- issue 53, section A: README, install, speed, botorch, serve, sessions, study, robustness,
# decisions, acquisition (figures and tables taken off hand-typed prose)

# README.md
FIGURES["readme_replay_people"] = Figure("replay/replay.json", "meta.people")
FIGURES["readme_calib_trials"] = Figure("person_calibration.json", "settings.trials")

# docs/install.md
FIGURES["install_fast_path_build"] = Figure(
    "fast_path/first_call.json", "rows.build (fast_path.build, empty cache).compile_wall_s", "{:.0f} s"
)

# docs/serve.md
FIGURES["serve_open_session_kb"] = Figure("serve/soak.json", "restart.open_session_kb_slope", "{:.0f} kB")
FIGURES["serve_rss_last_mb"] = Figure("serve/soak.json", "summary.rss_kb_first_last_max.1", "kb_mb")
FIGURES["serve_rss_max_mb"] = Figure("serve/soak.json", "summary.rss_kb_first_last_max.2", "kb_mb")
FIGURES["serve_rss_restart_mb"] = Figure("serve/soak.json", "restart.rss_kb_after_restart", "kb_mb")
FIGURES["serve_kill_wall"] = Figure("serve/kill.json", "wall_s", "{:.0f} s")
FIGURES["serve_timing_median"] = Figure("serve/timing.json", "summary.median_server_ms", "{:.0f} ms")
FIGURES["serve_timing_p90"] = Figure("serve/timing.json", "summary.p90_server_ms", "{:.0f} ms")
FIGURES["serve_timing_last50"] = Figure("serve/timing.json", "summary.median_server_ms_last_50", "{:.0f} ms")
FIGURES["serve_timing_round_trip"] = Figure("serve/timing.json", "summary.median_round_trip_ms", "{:.0f} ms")

# docs/sessions.md
_SCALE = "sessions/session_scale.csv"
for _op in ("answer", "undo", "resume"):
    FIGURES[f"sessions_more_{_op}"] = Figure(
        "sessions/session_scale.json", f"ms_more_at_1000_than_at_10.{_op}", "{:.1f} ms"
    )
    FIGURES[f"sessions_prev_{_op}_1000"] = Figure(
        _SCALE, f"seconds@answers=1000,code=previous (replay),operation={_op}", "{:.1f} s"
    )

# docs/botorch.md
FIGURES["botorch_own_pref"] = Figure("botorch_own_tests.json", "summary.PreferenceGP")
FIGURES["botorch_own_pair"] = Figure("botorch_own_tests.json", "summary.PairwiseGP")
FIGURES["botorch_own_total"] = Figure("botorch_own_tests.json", "total")
_BT_PBO, _BT_BOPE, _BT_SHARE = (
    "botorch_tutorials_preference_bo.json",
    "botorch_tutorials_bope.json",
    "botorch_tutorials_bope_share.json",
)
for _tag, _file, _phases in (
    ("pbo", _BT_PBO, ("preference_fit", "eubo_optimize")),
    ("bope", _BT_BOPE, ("preference_fit", "eubo_optimize", "learned_objective_acqf", "outcome_fit")),
):
    for _m, _short in (("PairwiseGP", "pair"), ("PreferenceGP", "pref")):
        FIGURES[f"botorch_{_tag}_cpu_{_short}"] = Figure(_file, f"phases.{_m}.cpu_s", "{:.1f} s")
        for _ph in _phases:
            _key = {"preference_fit": "fit", "eubo_optimize": "eubo"}.get(_ph, _ph) if _tag == "pbo" else _ph
            FIGURES[f"botorch_{_tag}_{_key}_{_short}"] = Figure(_file, f"phases.{_m}.phase_cpu_s.{_ph}", "{:.1f} s")
            FIGURES[f"botorch_{_tag}_{_key}_share_{_short}"] = Figure(_file, f"phases.{_m}.share.{_ph}", "{:.0%}")
_BT_FIRST = {"pbo": (_BT_PBO, "regret"), "bope": (_BT_BOPE, "EUBO-zeta_util")}
for _tag, (_file, _metric) in _BT_FIRST.items():
    FIGURES[f"botorch_{_tag}_cpu_ratio"] = Figure(_file, f"{_metric}.cpu_time_ratio", "{:.2f}×")
    FIGURES[f"botorch_{_tag}_wall_ratio"] = Figure(_file, f"{_metric}.wall_time_ratio", "{:.2f}×")
    FIGURES[f"botorch_{_tag}_wall_pair"] = Figure(_file, f"{_metric}.wall_s_PairwiseGP", "{:.0f} s")
    FIGURES[f"botorch_{_tag}_wall_pref"] = Figure(_file, f"{_metric}.wall_s_PreferenceGP", "{:.0f} s")
FIGURES["botorch_pbo_auc_p_worse"] = Figure(_BT_PBO, "auc_regret.p_worse", "{:.2f}")
FIGURES["botorch_pbo_final_p_worse"] = Figure(_BT_PBO, "regret.p_worse", "{:.2f}")
FIGURES["botorch_pbo_final_p_wilcoxon"] = Figure(_BT_PBO, "regret.p_wilcoxon", "{:.2f}")
FIGURES["botorch_pbo_auc_p_wilcoxon"] = Figure(_BT_PBO, "auc_regret.p_wilcoxon", "{:.2f}")
for _name, _metric in (
    ("eubo_util", "EUBO-zeta_util"),
    ("random_util", "Random-f_util"),
    ("eubo_last", "EUBO-zeta_last_check"),
    ("random_last", "Random-f_last_check"),
):
    FIGURES[f"botorch_bope_p_{_name}"] = Figure(_BT_BOPE, f"{_metric}.p_worse", "{:.2f}")
for _m, _short in (("PairwiseGP", "pair"), ("PreferenceGP", "pref")):
    for _ph, _p in (("eubo_zeta", "eubo"), ("learned_objective", "lo")):
        FIGURES[f"botorch_share_{_p}_{_short}"] = Figure(_BT_SHARE, f"{_m}.{_ph}.preference_share", "{:.0%}")
        FIGURES[f"botorch_share_{_p}_post_{_short}"] = Figure(_BT_SHARE, f"{_m}.{_ph}.preference_posterior", "ms")
        FIGURES[f"botorch_share_{_p}_cpu_{_short}"] = Figure(_BT_SHARE, f"{_m}.{_ph}.cpu_s", "ms")
    FIGURES[f"botorch_share_eubo_outcome_{_short}"] = Figure(_BT_SHARE, f"{_m}.eubo_zeta.outcome_sample", "ms")
# the tutorials' outcomes (mean and s.e. over seeds), and the repeated pairs (issue 53)
for _m, _short in (("PairwiseGP", "pair"), ("PreferenceGP", "pref")):
    for _tag, _file, _name, _metric in (
        ("pbo", _BT_PBO, "regret", "regret"),
        ("pbo", _BT_PBO, "auc", "auc_regret"),
        ("bope", _BT_BOPE, "eubo_util", "EUBO-zeta_util"),
        ("bope", _BT_BOPE, "random_util", "Random-f_util"),
        ("bope", _BT_BOPE, "eubo_last", "EUBO-zeta_last_check"),
    ):
        FIGURES[f"botorch_{_tag}_{_name}_{_short}"] = Figure(_file, f"{_metric}.{_m}_mean", "{:.3f}")
        FIGURES[f"botorch_{_tag}_{_name}_sem_{_short}"] = Figure(_file, f"{_metric}.{_m}_sem", "{:.3f}")
    FIGURES[f"botorch_pbo_repeats_{_short}"] = Figure(_BT_PBO, f"repeats.{_m}")
    FIGURES[f"botorch_pbo_proposals_{_short}"] = Figure(_BT_PBO, f"proposals.{_m}")

# docs/robustness.md
FIGURES["robustness_slowest_fit"] = Figure("hostile_fits.json", "rows.79.seconds", "{:.0f} s")

# docs/speed.md: the compiled path's loaded run, one table per task
_S = "{:.3g} s"
for _task in ("mode", "fit", "eubo"):
    TABLES[f"speed_quick_{_task}"] = Table(
        "fast_path/speed_pairwise_quick_loaded.csv",
        (
            ("n (p = 2n)", "n", "{}"),
            ("torchpref (`auto`)", "torchpref_s", _S),
            ("torch solver (`off`)", "torchpref_torch_s", _S),
            ("PairwiseGP", "pairwisegp_s", _S),
            ("botorch-rust", "botorch_rust_s", _S),
            ("vs PairwiseGP", "ratio_pairwisegp", "{:.3g}×"),
            ("vs botorch-rust", "ratio_botorch_rust", "{:.3g}×"),
        ),
        where=(("task", _task),),
    )

# docs/install.md: the recorded test runs (tests/conftest.py, TORCHPREF_RECORD_TESTS);
# the recorded test runs (TORCHPREF_RECORD_TESTS, tests/conftest.py): make test and make test-slow
for _run in ("default", "slow"):
    _file = f"test_runs/{_run}.json"
    FIGURES[f"install_tests_{_run}_wall"] = Figure(_file, "wall_s", "{:.0f} s")
    FIGURES[f"install_tests_{_run}_load"] = Figure(_file, "stamp.load_avg.0", "{:.1f}")
    FIGURES[f"install_tests_{_run}_commit"] = Figure(_file, "stamp.commit", "{:.7}")
    for _k in ("passed", "failed", "skipped", "xfailed", "errors"):
        FIGURES[f"install_tests_{_run}_{_k}"] = Figure(_file, f"counts.{_k}", "{:,}")

FIGURES["speed_kernel_20"] = Figure(_SPEED, "torchpref_s@task=kernel,n=20", "ms")
FIGURES["speed_mode_20_rust_s"] = Figure(_SPEED, "botorch_rust_s@task=mode,n=20", "ms")
_SERVED = "served_answer/served_answer.json"  # benchmarks/speed/served_answer.py (issue 52)
FIGURES["served_default_p50"] = Figure(_SERVED, "summary.default.served_ms_p50", "{:.1f} ms")
FIGURES["served_default_p99"] = Figure(_SERVED, "summary.default.served_ms_p99", "{:.1f} ms")
FIGURES["served_ucbc_p50"] = Figure(_SERVED, "summary.ucbc.served_ms_p50", "{:.1f} ms")
FIGURES["served_ucbc_p99"] = Figure(_SERVED, "summary.ucbc.served_ms_p99", "{:.1f} ms")
FIGURES["served_ratio"] = Figure(_SERVED, "default_over_ucbc_p50", "{:.1f}×")
FIGURES["served_load"] = Figure(_SERVED, "load_average.0", "{:.1f}")
_SOAK_BEFORE = "serve/soak_before.json"  # the soak before issue 52 (docs/serve.md)
FIGURES["soak_before_load"] = Figure(_SOAK_BEFORE, "load_average.0", "{:.1f}")
FIGURES["soak_before_ms_p50"] = Figure(_SOAK_BEFORE, "summary.answer_ms_p50_p95_p99.0", "{:.0f}")
FIGURES["soak_before_ms_p99"] = Figure(_SOAK_BEFORE, "summary.answer_ms_p50_p95_p99.2", "{:.0f}")
FIGURES["soak_before_cpu_ms"] = Figure(_SOAK_BEFORE, "summary.server_cpu_s_per_answer", "ms")
FIGURES["soak_cpu_p50"] = Figure("serve/soak.json", "summary.answer_cpu_ms_p50_p95_p99_max.0", "{:.1f}")
FIGURES["soak_cpu_p99"] = Figure("serve/soak.json", "summary.answer_cpu_ms_p50_p95_p99_max.2", "{:.1f}")
# --- end of section A

MARKER = re.compile(r"<!-- fig:(?P<name>[\w]+) -->(?P<text>.*?)<!-- /fig -->")
TABLE_MARKER = re.compile(r"<!-- table:(?P<name>\w+) -->\n(?P<text>.*?)\n<!-- /table -->", re.S)
TABLE_STALE_NOTE = "*(measured on an older version)*"
TABLE_UNSTAMPED_NOTE = "*(an older run, unstamped)*"

# --- issue 53, section B: suite, results, laplace, lake, wave, likelihoods, population,
# real_raters, selection, ax (figures and tables taken off hand-typed prose)
# docs/results.md
_Q = "paired_tests.queries"
_E = "paired_tests.effort"
_WSEL = "wave_selector/wave_summary.json"
_ORD = "ordinal.json"
_ORDT = "summary.ties"
_ORDL = "summary.likert"
FIGURES.update(
    {
        "results_wave_p_ucbc_ucb_wrms": Figure(_WAVE, f"{_Q}.UCBC vs UCB ratings.wrms.p_wilcoxon", "{:.3f}"),
        "results_wave_p_ucbc_rankings_tp": Figure(_WAVE, f"{_Q}.UCBC vs random rankings.tp.p_wilcoxon", "{:.1f}"),
        "results_wave_p_info_rankings_tp": Figure(
            _WAVE, f"{_Q}.info per effort vs random rankings.tp.p_wilcoxon", "sci"
        ),
        "results_wave_p_info_ucbc_wrms_effort": Figure(_WAVE, f"{_E}.info per effort vs UCBC.wrms.p_wilcoxon", "sci"),
        "results_wave_p_info_ucbc_tp_effort": Figure(_WAVE, f"{_E}.info per effort vs UCBC.tp.p_wilcoxon", "{:.3f}"),
        "results_wave_p_info_profile_wrms": Figure(
            _WSEL, f"{_Q}.info per effort vs profile per effort.wrms.p_wilcoxon", "{:.3f}"
        ),
        "results_speed_wave_ours": Figure("speed_wave.json", "median.torchpref.compute_s", "{:.1f} s"),
        "results_speed_wave_authors": Figure("speed_wave.json", "median.authors.compute_s", "{:.1f} s"),
        "results_speed_wave_ratio": Figure("speed_wave.json", "speedup.compute_s", "{:.1f}×"),
        "results_speed_wave_ours_cmd": Figure("speed_wave.json", "median.torchpref.command_s", "{:.1f} s"),
        "results_speed_wave_authors_cmd": Figure("speed_wave.json", "median.authors.command_s", "{:.1f} s"),
        "results_speed_wave_ratio_cmd": Figure("speed_wave.json", "speedup.command_s", "{:.1f}×"),
        "results_lake_wall": Figure("lake_summary.json", "wall_time_s", "{:.1f} s"),
        "results_lake1_ucb": Figure("lake_summary.json", "share_rated_5.UCB ratings", "percent"),
        "results_lake1_info": Figure("lake_summary.json", "share_rated_5.info per effort", "percent"),
        "results_lake1_ucbc": Figure("lake_summary.json", "share_rated_5.UCBC", "percent"),
        "results_lake1_random": Figure("lake_summary.json", "share_rated_5.random ratings", "percent"),
        "results_lake1_p_error5": Figure(
            "lake_summary.json", "paired_tests.UCBC vs UCB ratings.error5.p_wilcoxon", "{:.3f}"
        ),
        "results_lakes10_variance": Figure(
            "lakes10_selector/lake_summary.json", "share_rated_5.variance per effort", "percent"
        ),
        "results_lakes10_ucb": Figure("lakes10_selector/lake_summary.json", "share_rated_5.UCB ratings", "percent"),
        "results_lakes10_profile": Figure(
            "lakes10_selector/lake_summary.json", "share_rated_5.profile per effort", "percent"
        ),
        "results_lakes10_info": Figure(
            "lakes10_selector/lake_summary.json", "share_rated_5.info per effort", "percent"
        ),
        "results_lakes10_plan_ok": Figure(
            "lakes10_selector/lake_summary.json", "planning.UCBC.at_least_as_good", "percent2"
        ),
        "results_lakes10_plan_better": Figure(
            "lakes10_selector/lake_summary.json", "planning.UCBC.strictly_better", "percent2"
        ),
        "results_lakes20_wall": Figure("lakes20/lake_summary.json", "wall_time_s", "{:.1f} s"),
        "results_lakes20_plan_ok": Figure("lakes20/lake_summary.json", "planning.UCBC.at_least_as_good", "percent"),
        "results_lakes20_plan_better": Figure("lakes20/lake_summary.json", "planning.UCBC.strictly_better", "percent2"),
        "results_ordinal_wall": Figure(_ORD, "meta.wall_time_s", "{:.0f} s"),
        "results_ordinal_ties_p_bump25_regret": Figure(_ORD, f"{_ORDT}.bump 25%.used - ignored/regret.p_ttest", "sci"),
        "results_ordinal_p_wave": Figure(_ORD, f"{_ORDL}.wave.ordinal - beta/wrms.p_ttest", "sci"),
        "results_ordinal_p_partial": Figure(_ORD, f"{_ORDL}.partial.ordinal - beta/wrms.p_ttest", "sci"),
        "results_ordinal_p_bump": Figure(_ORD, f"{_ORDL}.bump.ordinal - beta/wrms.p_ttest", "sci"),
        "results_ordinal_p_lake": Figure(_ORD, f"{_ORDL}.lake.ordinal - beta/wrms.p_ttest", "sci"),
        "results_ordinal_p_lake_tp": Figure(_ORD, f"{_ORDL}.lake.ordinal - beta/tp.p_ttest", "sci"),
        "results_ordinal_p_learned_partial": Figure(
            _ORD, f"{_ORDL}.partial.ordinal-learned - beta/wrms.p_ttest", "sci"
        ),
        "results_ordinal_p_learned_bump": Figure(_ORD, f"{_ORDL}.bump.ordinal-learned - beta/wrms.p_ttest", "sci"),
        "results_ordinal_p_learned_lake_tp": Figure(_ORD, f"{_ORDL}.lake.ordinal-learned - beta/tp.p_ttest", "sci"),
    }
)

# docs/real_raters.md: the SUSHI replay's budgets in seconds (inputs, written from the file they were run with)
for _i in range(5):
    FIGURES[f"real_raters_budget_{_i}"] = Figure("sushi/sushi.json", f"summary.budgets.{_i}", "{} s")
# docs/population.md: the memory of the 1,000-people fit over 300 shared items (population_scale.py)
_PSCALE = "population/population_scale.json"
FIGURES["population_scale_peak_gb"] = Figure(_PSCALE, "peak_memory_gb.master", "{:.2f} GB")
FIGURES["population_scale_before_gb"] = Figure(_PSCALE, "peak_memory_before_fit_gb", "{:.2f} GB")
FIGURES["population_scale_estimate_gb"] = Figure(_PSCALE, "memory_estimate_gb", "{:.2f} GB")
# docs/likelihoods.md: the person calibration (benchmarks/studies/person_calibration.py)
_PCAL = "person_calibration.json"
FIGURES["likelihoods_pcal_wall"] = Figure(_PCAL, "wall_s", "{:.0f} s")
for _m in ("wrms", "tp", "regret"):
    FIGURES[f"likelihoods_pcal_p_{_m}"] = Figure(_PCAL, f"recovery.paired.{_m}.wilcoxon_p", "{:.2g}")
    FIGURES[f"likelihoods_pcal_ideal_p_{_m}"] = Figure(_PCAL, f"ideal.{_m}.wilcoxon_p", "{:.2g}")
# docs/wave.md: the table at 20 queries, the ratings asked, the paired tests at equal effort, the
# one-process run (benchmarks/speed/speed_wave.py --workers 1, speed_wave_processes/)
TABLES["wave_final"] = Table(
    _WAVE,
    (
        ("strategy", "__key__", "{}"),
        ("WRMS", "wrms.0", "{:.4f}"),
        ("± s.e.", "wrms.1", "{:.4f}"),
        ("true positives", "tp.0", "{:.2f}"),
        ("± s.e.", "tp.1", "{:.2f}"),
    ),
    rows="final",
)
for _s, _n in (("UCBC", "ucbc"), ("info per effort", "info")):
    FIGURES[f"wave_ratings_{_n}"] = Figure(_WAVE, f"fraction_ratings.{_s}", "percent2")
for _pair, _m, _n in (
    ("info per effort vs random rankings", "tp", "info_rankings_tp"),
    ("info per effort vs UCB ratings", "wrms", "info_ucb_wrms"),
    ("info per effort vs UCB ratings", "tp", "info_ucb_tp"),
    ("UCBC vs UCB ratings", "wrms", "ucbc_ucb_wrms"),
):
    FIGURES[f"wave_effort_p_{_n}"] = Figure(_WAVE, f"{_E}.{_pair}.{_m}.p_wilcoxon", "{:.2g}")
_WPROC = "speed_wave_processes/speed_wave.json"
FIGURES["wave_proc_cpu_2"] = Figure(_WPROC, "median.torchpref.cpu_s", "{:.1f} s")
FIGURES["wave_proc_cpu_1"] = Figure(_WPROC, "median.torchpref_1_process.cpu_s", "{:.1f} s")
FIGURES["wave_proc_wall_2"] = Figure(_WPROC, "median.torchpref.compute_s", "{:.0f} s")
FIGURES["wave_proc_wall_1"] = Figure(_WPROC, "median.torchpref_1_process.compute_s", "{:.0f} s")
# docs/lake.md: the one-lake run's paired tests and plans, the 10-lake planning run (benchmarks/results/lakes/)
_L1, _L10, _L20 = "lake_summary.json", "lakes/lake_summary.json", "lakes20/lake_summary.json"
for _pair, _n in (
    ("UCBC vs random ratings", "random"),
    ("UCBC vs UCB ratings", "ucb"),
    ("UCBC vs info per effort", "info"),
):
    for _m in ("error5", "wrms"):
        FIGURES[f"lake_p_{_n}_{_m}"] = Figure(_L1, f"paired_tests.{_pair}.{_m}.p_wilcoxon", "{:.2g}")
FIGURES["lake_one_plan_ok"] = Figure(_L1, "planning.UCBC.at_least_as_good", "percent")
FIGURES["lake_one_plan_better"] = Figure(_L1, "planning.UCBC.strictly_better", "percent")
FIGURES["lake_many_wall"] = Figure(_L10, "wall_time_s", "{:.0f} s")
FIGURES["lake_many_scenarios"] = Figure(_L10, "scenario_time_s", "{:.1f} s")
FIGURES["lake_many_plan_ok"] = Figure(_L10, "planning.UCBC.at_least_as_good", "percent2")
FIGURES["lake_many_plan_better"] = Figure(_L10, "planning.UCBC.strictly_better", "percent2")
FIGURES["lake_many_p_levels"] = Figure(_L10, "planning.UCBC.paired.p_wilcoxon", "{:.2f}")
FIGURES["lake_20_scenarios"] = Figure(_L20, "scenario_time_s", "{:.0f} s")
TABLES["lake_plan_per_lake"] = Table(
    _L10,
    (
        ("lake", "__key__", "{}"),
        ("planned ≥ pick", "planning.UCBC.at_least_as_good", "percent"),
        ("strictly better", "planning.UCBC.strictly_better", "percent"),
        ("optimised path kept (of 20)", "planning.UCBC.sources.planned", "{}"),
        ("planned level", "planning.UCBC.planned_level_mean", "{:.2f}"),
        ("pick level", "planning.UCBC.pick_level_mean", "{:.2f}"),
    ),
    rows="per_lake",
)
# docs/ax.md: Ax's own tests of its preference path (benchmarks/parity/ax_upstream_tests.py)
FIGURES["ax_upstream_ran"] = Figure("ax/upstream_tests.json", "modes.documented.counts.ran", "{} tests")
# docs/laplace.md: our mode and fit against their floors (benchmarks/speed/speed_floor.py)
TABLES["laplace_floor"] = Table(
    "speed_floor.csv",
    (
        ("n", "n", "{}"),
        ("mode factorisations", "mode_factorisations", "{}"),
        ("mode evaluations", "mode_evaluations", "{}"),
        ("our construction + mode (s)", "ours_mode_s", "{:.3g}"),
        ("the same, torch path (s)", "ours_mode_torch_s", "{:.3g}"),
        ("solve (s)", "ours_solve_s", "{:.3g}"),
        ("its floor, torch (s)", "floor_torch_mode_s", "{:.3g}"),
        ("LAPACK (s)", "floor_lapack_mode_s", "{:.3g}"),
        ("ratio, torch", "mode_over_torch_floor", "{:.1f}×"),
        ("LAPACK", "mode_over_lapack_floor", "{:.1f}×"),
        ("torch path, torch", "mode_torch_path_over_torch_floor", "{:.1f}×"),
        ("fit L-BFGS evaluations", "fit_lbfgs_evaluations", "{}"),
        ("fit factorisations", "fit_factorisations", "{}"),
        ("our fit (s)", "ours_fit_s", "{:.3g}"),
        ("its floor, torch (s)", "floor_torch_fit_s", "{:.3g}"),
        ("LAPACK (s)", "floor_lapack_fit_s", "{:.3g}"),
        ("ratio, torch", "fit_over_torch_floor", "{:.1f}×"),
        ("LAPACK", "fit_over_lapack_floor", "{:.1f}×"),
    ),
)
for _c, _fmt in (
    ("mode_over_torch_floor", "{:.1f}×"),
    ("mode_over_lapack_floor", "{:.1f}×"),
    ("solve_over_torch_floor", "{:.1f}×"),
    ("mode_torch_path_over_torch_floor", "{:.1f}×"),
):
    FIGURES[f"laplace_floor_{_c}_100"] = Figure("speed_floor.csv", f"{_c}@n=100", _fmt)
TABLES["laplace_mixed_fits"] = Table(
    "mixed_lengthscale.json",
    (
        ("model", "__key__", "{}"),
        ("lengthscales", "lengthscale.0", "{:.3f}"),
        ("", "lengthscale.1", "{:.3f}"),
        ("outputscale", "outputscale", "{:.3g}"),
        ("evidence + priors", "evidence_with_priors", "{:.1f}"),
        ("L-BFGS evaluations", "lbfgs_evaluations", "{}"),
        ("fit CPU", "fit_cpu_s", "{:.1f} s"),
    ),
    rows="arms",
)
_LARGE = "speed_large_fit.json"
FIGURES["laplace_large_eval"] = Figure(_LARGE, "evaluation_cpu_s", "{:.2f} s")
for _part in ("resolve", "evidence", "kernel", "backward"):
    FIGURES[f"laplace_large_{_part}"] = Figure(_LARGE, f"evaluation_parts_cpu_s.{_part}", "{:.2f} s")
# --- end of section B

# --- issue 53, section C: docs/suite.md (the suite, issue 30's replay and candidates, the realistic raters,
# the lake operators, the selectors on the lakes and the wave): tables computed from the files' nested results
ABBREVIATIONS = {
    "UCB ratings": "UCBr", "random rankings": "RRk", "random ratings": "RRt", "info per effort": "IPE",
    "top & level info": "TLI", "variance per effort": "VPE", "profile per effort": "PPE", "clipped profile": "CPE",
}  # fmt: skip
"""The short names a verdict grid (:func:`verdict_grid`) gives the strategy that beat the row's."""
_METRICS = ("wrms", "tp", "regret")


def replay_rows(data: dict) -> list[dict]:
    """A replay's rows (``torchpref reproduce replay``): per data set and selector, each metric's area
    (``accuracy``, ``log_loss``, ``top1``) and, for a selector other than the random baseline, the
    mean paired difference from random, the (person, split) pairs where it is higher / lower
    (accuracy and top-1) and the two-sided Wilcoxon p, as one cell's text."""
    rows = []
    for data_set, selectors in data["summary"].items():
        for selector, result in selectors.items():
            row: dict[str, object] = {"data set": data_set, "selector": selector}
            for metric in ("accuracy", "log_loss", "top1"):
                r = result[metric]
                text = f"{r['area']:.3f}"
                if "p" in r:
                    pairs = f", {r['wins']} / {r['losses']}" if metric != "log_loss" else ""
                    text += f" ({r['diff']:+.3f}{pairs}, p = {r['p']:.2g})"
                row[metric] = text
            rows.append(row)
    return rows


def _cells(data: dict) -> list[tuple[str, int, str, str, str]]:
    """A suite summary's verdict cells: ``(family/condition, checkpoint's position, checkpoint, metric,
    strategy)`` for every strategy best or tied in the cell."""
    out = []
    for fc, checkpoints in data["verdicts"].items():
        for i, (checkpoint, metrics) in enumerate(checkpoints.items()):
            for metric, verdict in metrics.items():
                out += [(fc, i, checkpoint, metric, s) for s, st in verdict["status"].items() if st in ("best", "tied")]
    return out


def suite_counts(data: dict) -> list[dict]:
    """Per strategy of a suite summary (``suite_summary.json``): how many (family, condition,
    checkpoint, metric) cells of its ``verdicts`` it is best or tied in (two-sided Wilcoxon on the
    paired trials, p > 0.05): per checkpoint (``c0`` … ``c3``, the file's order: 10 and 20 queries,
    then the two effort budgets), in all (``total``; equal to the file's ``best_or_tied``), after
    queries (``queries``), at equal effort (``effort``), at equal effort per metric (``effort wrms`` …)
    and per condition (``effort fixed``, ``effort learned``), and per metric over every checkpoint
    (``wrms`` …); ``ratings``: its mean share of ratings over the family-conditions."""
    cells = _cells(data)
    rows = []
    for strategy in data["best_or_tied"]:
        mine = [c for c in cells if c[4] == strategy]
        shares = [f[strategy] for f in data["fraction_ratings"].values()]
        row: dict[str, object] = {"strategy": strategy, "ratings": sum(shares) / len(shares), "total": len(mine)}
        for i in range(4):
            row[f"c{i}"] = sum(c[1] == i for c in mine)
        row["queries"] = sum(c[2].startswith("queries") for c in mine)
        row["effort"] = sum(c[2].startswith("effort") for c in mine)
        for metric in _METRICS:
            row[metric] = sum(c[3] == metric for c in mine)
            row[f"effort {metric}"] = sum(c[3] == metric and c[2].startswith("effort") for c in mine)
        for condition in ("fixed", "learned"):
            row[f"effort {condition}"] = sum(c[0].endswith("/" + condition) and c[2].startswith("effort") for c in mine)
        rows.append(row)
    return rows


def verdict_grid(strategy: str) -> Callable[[dict], list[dict]]:
    """The rows of a suite summary's verdicts for ``strategy``: per family-condition (``case``), its
    share of ratings and, per checkpoint and metric (``c0 wrms`` …, :func:`suite_counts`'s order),
    **best**, tied, or the short name (:data:`ABBREVIATIONS`) of the best strategy where it is worse."""

    def rows(data: dict) -> list[dict]:
        out = []
        for fc, checkpoints in data["verdicts"].items():
            row: dict[str, object] = {"case": fc, "ratings": data["fraction_ratings"][fc][strategy]}
            for i, metrics in enumerate(checkpoints.values()):
                for metric, verdict in metrics.items():
                    status, best = verdict["status"][strategy], verdict["best"]
                    text = {"best": "**best**", "tied": "tied"}.get(status, ABBREVIATIONS.get(best, best))
                    row[f"c{i} {metric}"] = text
            out.append(row)
        return out

    return rows


def lake_rows(data: dict) -> list[dict]:
    """Per strategy of a lake summary (``lake_summary.json``): its share of ratings, the final error
    on the paths rated 5 and WRMS (``mean ± s.e.`` text), the share of trials whose chosen path is
    rated 5, and ``seconds``: what its queries cost per trial under the trajectories effort model
    (``EffortModel.trajectories()``: each query a rating or a best-of-``m`` at the strategy's mean
    share of ratings)."""
    from torchpref.data.effort import EffortModel

    effort, m, queries = EffortModel.trajectories(), data["settings"]["m"], data["queries"]
    rows = []
    for strategy, final in data["final"].items():
        r = data["fraction_ratings"][strategy]
        rows.append(
            {
                "strategy": strategy,
                "ratings": r,
                "error5": "{:.3f} ± {:.3f}".format(*final["error5"]),
                "wrms": "{:.3f} ± {:.3f}".format(*final["wrms"]),
                "rated5": data["share_rated_5"][strategy],
                "seconds": queries * (r * effort.rating() + (1 - r) * effort.ranking(m)),
            }
        )
    return rows


def per_lake_rows(data: dict) -> list[dict]:
    """Per lake of a many-lakes summary: each strategy's share of trials whose chosen path is rated 5
    (the strategy's name the key)."""
    return [{"lake": lake, **result["share_rated_5"]} for lake, result in data["per_lake"].items()]


def paired_rows(at: str = "", names: tuple[str, ...] = ()) -> Callable[[dict], list[dict]]:
    """The paired tests at the dotted path ``at`` (``{"A vs B": {metric: test}}``) as rows: ``pair``
    and, per metric, ``<metric> diff`` (the mean paired difference, A − B) and ``<metric> p`` (the
    two-sided Wilcoxon p); only the pairs naming one of ``names``, when given."""

    def rows(data: dict) -> list[dict]:
        value: Any = dotted(data, at)
        out = []
        for pair, tests in value.items():
            if names and not any(n in pair.split(" vs ") for n in names):
                continue
            row: dict[str, object] = {"pair": pair}
            for metric, test in tests.items():
                row[f"{metric} diff"], row[f"{metric} p"] = test["mean_diff"], test["p_wilcoxon"]
            out.append(row)
        return out

    return rows


def final_rows(data: dict) -> list[dict]:
    """Per strategy of a wave summary: its final WRMS and true positives (``mean ± s.e.`` text) and its
    share of ratings."""
    return [
        {
            "strategy": s,
            "wrms": "{:.4f} ± {:.4f}".format(*final["wrms"]),
            "tp": "{:.2f} ± {:.2f}".format(*final["tp"]),
            "ratings": data["fraction_ratings"][s],
        }
        for s, final in data["final"].items()
    ]


def mc_noise_rows(data: dict) -> list[dict]:
    """Per selector and sample count of ``profile_mc_noise.json``: the share of the best pick's value its
    picks keep (the mean over model states, and the states' least and largest means) and how often a
    state's most frequent kind of query is picked (mean over states)."""
    groups: dict[tuple[bool, int], list[dict]] = {}
    for state in data["states"]:
        groups.setdefault((state["clipped"], state["samples"]), []).append(state)
    rows = []
    for (clipped, samples), states in groups.items():
        ratios = [s["mean_ratio"] for s in states]
        rows.append(
            {
                "selector": "clipped profile" if clipped else "profile per effort",
                "samples": samples,
                "mean": sum(ratios) / len(ratios),
                "min": min(ratios),
                "max": max(ratios),
                "same kind": sum(s["share_same_kind"] for s in states) / len(states),
                "states": len(states),
            }
        )
    return rows


_SEL_COUNTS = (
    ("strategy", "strategy", "{}"),
    ("ratings (mean)", "ratings", "{:.0%}"),
    ("per query (of 60)", "queries", "{}"),
    ("**equal seconds** (of 60)", "effort", "{}"),
    ("equal seconds: WRMS", "effort wrms", "{}"),
    ("TP", "effort tp", "{}"),
    ("regret (of 20 each)", "effort regret", "{}"),
    ("equal seconds: fixed", "effort fixed", "{}"),
    ("learned (of 30 each)", "effort learned", "{}"),
)
for _e in ("plain", "trajectories"):
    TABLES[f"suite_select30_{_e}"] = Table(f"suite_select30_{_e}/suite_summary.json", _SEL_COUNTS, rows=suite_counts)
    FIGURES[f"suite_select30_{_e}_wall"] = Figure(f"suite_select30_{_e}/suite_summary.json", "wall_time_s", "{:,.0f} s")
    FIGURES[f"suite_select30_{_e}_cpu"] = Figure(f"suite_select30_{_e}/suite_summary.json", "cpu_time_s", "{:,.0f} s")
    _b = (34, 68) if _e == "plain" else (134, 268)
    TABLES[f"suite_realistic_{_e}"] = Table(
        f"suite_realistic_{_e}/suite_summary.json",
        (
            ("strategy", "strategy", "{}"),
            ("ratings (mean)", "ratings", "{:.0%}"),
            ("q10", "c0", "{}"),
            ("q20", "c1", "{}"),
            (f"{_b[0]} s", "c2", "{}"),
            (f"{_b[1]} s (of 21 each)", "c3", "{}"),
            ("total (of 84)", "total", "{}"),
            ("equal seconds: WRMS", "effort wrms", "{}"),
            ("TP", "effort tp", "{}"),
            ("regret (of 14 each)", "effort regret", "{}"),
        ),
        rows=suite_counts,
    )
    FIGURES[f"suite_realistic_{_e}_wall"] = Figure(
        f"suite_realistic_{_e}/suite_summary.json", "wall_time_s", "{:,.0f} s"
    )
    FIGURES[f"suite_realistic_{_e}_cpu"] = Figure(f"suite_realistic_{_e}/suite_summary.json", "cpu_time_s", "{:,.0f} s")
for _name, _file in (("suite_replay", "replay/replay.json"), ("suite_replay_clipped", "replay_clipped/replay.json")):
    TABLES[_name] = Table(
        _file,
        (
            ("data set", "data set", "{}"),
            ("selector", "selector", "{}"),
            ("area, held-out accuracy (± vs random, higher / lower, p)", "accuracy", "{}"),
            ("log loss (lower is better; ± vs random, p)", "log_loss", "{}"),
            ("area, held-out top-1 (± vs random, higher / lower, p)", "top1", "{}"),
        ),
        rows=replay_rows,
    )
FIGURES["suite_replay_pairs"] = Figure("replay/replay.json", "summary.electricity.random.pairs")
FIGURES["suite_replay_clipped_seconds"] = Figure("replay_clipped/replay.json", "meta.seconds", "{:.0f} s")
FIGURES["suite_replay_clipped_load_lo"] = Figure(
    "replay_clipped/replay.json", "meta.load_average_start_end.0", "{:.1f}"
)
FIGURES["suite_replay_clipped_load_hi"] = Figure(
    "replay_clipped/replay.json", "meta.load_average_start_end.1", "{:.1f}"
)
_LAKE_COLUMNS = (
    ("strategy", "strategy", "{}"),
    ("ratings", "ratings", "{:.0%}"),
    ("error on the paths rated 5", "error5", "{}"),
    ("WRMS", "wrms", "{}"),
    ("chosen path rated 5", "rated5", "{:.1%}"),
)
for _op in ("paper", "realistic"):
    _f = f"lake_operator_{_op}/lake_summary.json"
    TABLES[f"suite_lake_operator_{_op}"] = Table(
        _f, (*_LAKE_COLUMNS, ("seconds per trial (trajectories model)", "seconds", "{:.0f}")), rows=lake_rows
    )
    TABLES[f"suite_lake_operator_{_op}_tests"] = Table(
        _f,
        (
            ("pair (A vs B)", "pair", "{}"),
            ("error-5: A − B", "error5 diff", "{:+.3f}"),
            ("p", "error5 p", "{:.2g}"),
            ("WRMS: A − B", "wrms diff", "{:+.3f}"),
            ("p", "wrms p", "{:.2g}"),
            ("chosen rating: A − B", "chosen_rating diff", "{:+.2f}"),
            ("p", "chosen_rating p", "{:.2g}"),
        ),
        rows=paired_rows("paired_tests"),
    )
    FIGURES[f"suite_lake_operator_{_op}_wall"] = Figure(_f, "wall_time_s", "{:,.0f} s")
_LK, _LKC = "lakes10_selector/lake_summary.json", "lakes10_selector_clipped/lake_summary.json"
TABLES["suite_lakes10"] = Table(_LK, _LAKE_COLUMNS, rows=lake_rows)
TABLES["suite_lakes10_clipped"] = Table(_LKC, _LAKE_COLUMNS, rows=lake_rows)
TABLES["suite_lakes10_per_lake"] = Table(
    _LK,
    (
        ("lake", "lake", "{}"),
        *((s, s, "{:.0%}") for s in ("UCBC", "random ratings", "UCB ratings", "info per effort")),
        *((s, s, "{:.0%}") for s in ("variance per effort", "profile per effort")),
    ),
    rows=per_lake_rows,
)
TABLES["suite_lakes10_clipped_per_lake"] = Table(
    _LKC, (("lake", "lake", "{}"), ("clipped profile", "clipped profile", "{:.0%}")), rows=per_lake_rows
)
FIGURES["suite_lakes10_wall"] = Figure(_LK, "wall_time_s", "{:,.0f} s")
FIGURES["suite_lakes10_clipped_wall"] = Figure(_LKC, "wall_time_s", "{:,.0f} s")
TABLES["suite_wave_selector"] = Table(
    _WSEL,
    (
        ("strategy", "strategy", "{}"),
        ("ratings", "ratings", "{:.0%}"),
        ("WRMS after 20 queries", "wrms", "{}"),
        ("true positives", "tp", "{}"),
    ),
    rows=final_rows,
)
for _at in ("queries", "effort"):
    TABLES[f"suite_wave_selector_{_at}"] = Table(
        _WSEL,
        (
            ("pair (A vs B)", "pair", "{}"),
            ("WRMS: A − B", "wrms diff", "{:+.4f}"),
            ("p", "wrms p", "{:.2g}"),
            ("TP: A − B", "tp diff", "{:+.2f}"),
            ("p", "tp p", "{:.2g}"),
        ),
        rows=paired_rows(f"paired_tests.{_at}", ("profile per effort", "clipped profile")),
    )
FIGURES["suite_wave_selector_wall"] = Figure(_WSEL, "wall_time_s", "{:.0f} s")
_S50 = "suite50/suite_summary.json"
TABLES["suite50_counts"] = Table(
    _S50,
    (
        ("strategy", "strategy", "{}"),
        ("queries 10", "c0", "{}"),
        ("queries 20", "c1", "{}"),
        ("effort 10", "c2", "{}"),
        ("effort 20 (of 54 each)", "c3", "{}"),
        ("total (of 216)", "total", "{}"),
        ("WRMS", "wrms", "{}"),
        ("TP", "tp", "{}"),
        ("regret (of 72 each)", "regret", "{}"),
    ),
    rows=suite_counts,
)
for _s, _n in (("profile per effort", "profile"), ("clipped profile", "clipped")):
    TABLES[f"suite50_grid_{_n}"] = Table(
        _S50,
        (
            ("family / condition", "case", "{}"),
            ("ratings", "ratings", "{:.0%}"),
            *(
                (f"{c}: {m}", f"c{i} {k}", "{}")
                for i, c in enumerate(("q10", "q20", "e10", "e20"))
                for k, m in zip(_METRICS, ("WRMS", "TP", "regret"), strict=True)
            ),
        ),
        rows=verdict_grid(_s),
    )
for _fc, _cp, _m, _s, _n in (
    ("hartmann3/learned", "queries 20", "tp", "clipped profile", "hartmann3_tp_clipped"),
    ("hartmann3/learned", "queries 20", "tp", "profile per effort", "hartmann3_tp_profile"),
):
    FIGURES[f"suite50_{_n}"] = Figure(_S50, f"verdicts.{_fc}.{_cp}.{_m}.mean.{_s}", "{:.3g}")
_MC = "profile_mc_noise.json"
TABLES["suite_mc_noise"] = Table(
    _MC,
    (
        ("selector", "selector", "{}"),
        ("samples", "samples", "{:,}"),
        ("share of the best pick's value kept (mean)", "mean", "{:.2f}"),
        ("least state", "min", "{:.2f}"),
        ("largest state", "max", "{:.2f}"),
        ("a state's most frequent kind picked", "same kind", "{:.0%}"),
    ),
    rows=mc_noise_rows,
)
FIGURES["suite_mc_noise_seeds"] = Figure(_MC, "seeds")
FIGURES["suite_mc_noise_reference"] = Figure(_MC, "reference_samples", "{:,}")
# --- end of section C
# speed, laplace, serve, sessions, study (issue 53)
# docs/speed.md: the quiet run's commit and loads, and how the libraries agree (speed_quiet/, fit_quality)
_SQ = "speed_quiet/speed_pairwise.json"
FIGURES["speedq_commit"] = Figure(_SQ, "stamp.commit", "{:.7}")
FIGURES["speedq_load_start"] = Figure(_SQ, "meta.load_average_at_start.0", "{:.1f}")
FIGURES["speedq_load_end"] = Figure(_SQ, "meta.load_average_at_end.0", "{:.1f}")
FIGURES["speedq_repeats"] = Figure(_SQ, "meta.repeats")
TABLES["speedq_agreement"] = Table(
    _SQ,
    (
        ("n", "n", "{}"),
        ("evidence: torchpref", "torchpref.evidence", "{:.5f}"),
        ("PairwiseGP", "pairwisegp.evidence", "{:.5f}"),
        ("botorch-rust", "botorch_rust.evidence", "{:.5f}"),
        ("outputscale: torchpref", "torchpref.outputscale", "{}"),
        ("PairwiseGP", "pairwisegp.outputscale", "{}"),
        ("botorch-rust", "botorch_rust.outputscale", "{}"),
        ("initial mode, from ours: PairwiseGP", "pairwisegp.max_abs_initial_mode_difference", "sci"),
        ("botorch-rust", "botorch_rust.max_abs_initial_mode_difference", "sci"),
        ("torch solver", "torchpref_torch.max_abs_initial_mode_difference", "sci"),
        ("fitted mode, from ours: PairwiseGP", "pairwisegp.max_abs_fitted_mode_difference", "sci"),
        ("botorch-rust", "botorch_rust.max_abs_fitted_mode_difference", "sci"),
    ),
    rows="fit_quality",
)
# docs/speed.md: the loaded quick run's loads, the first call, the compiled path against the floor
_QL = "fast_path/speed_pairwise_quick_loaded.json"
FIGURES["speed_quick_load_start"] = Figure(_QL, "meta.load_average_at_start.0", "{:.1f}")
FIGURES["speed_quick_load_end"] = Figure(_QL, "meta.load_average_at_end.0", "{:.1f}")
_FC = "fast_path/first_call.json"
FIGURES["speed_first_call_auto_second_cpu"] = Figure(_FC, "rows.auto, cache on disk.second_fit_cpu_s", "{:.2f} s")
FIGURES["speed_first_call_off_second_cpu"] = Figure(_FC, "rows.off.second_fit_cpu_s", "{:.2f} s")
_FF = "fast_path/speed_floor.json"
for _c in (
    "solve_over_torch_floor",
    "fit_over_torch_floor",
    "mode_over_torch_floor",
    "mode_torch_path_over_torch_floor",
    "fit_torch_path_over_torch_floor",
):
    FIGURES[f"speed_fastfloor_{_c}"] = Figure(_FF, f"rows.0.{_c}", "{:.2f}×")
FIGURES["speed_fastfloor_load"] = Figure(_FF, "meta.load_average_at_start.0", "{:.1f}")
# docs/laplace.md: the floor's load, torch.compile's step, the mixed fits and the large fit in prose
FIGURES["laplace_floor_load"] = Figure("speed_floor.json", "meta.load_average_at_start.0", "{:.1f}")
FIGURES["laplace_floor_load_end"] = Figure("speed_floor.json", "meta.load_average_at_end.0", "{:.1f}")
FIGURES["laplace_floor_mode_factorisations_100"] = Figure("speed_floor.csv", "mode_factorisations@n=100", "{:.0f}")
TABLES["laplace_compile"] = Table(
    "speed_compile.json",
    (
        ("n", "n", "{}"),
        ("eager step (s)", "eager_s", "{:.3g}"),
        ("compiled step (s)", "compiled_s", "{:.3g}"),
        ("eager / compiled", "speedup", "{:.2f}×"),
        ("compiled's first call at this size (s)", "first_call_at_size_s", "{:.3g}"),
        ("largest difference", "max_abs_difference", "sci"),
    ),
    rows="rows",
)
FIGURES["laplace_compile_cpu"] = Figure("speed_compile.json", "compilation.cpu_s", "{:.1f} s")
FIGURES["laplace_compile_compiler_cpu"] = Figure(
    "speed_compile.json", "compilation.compiler_processes_cpu_s", "{:.1f} s"
)
FIGURES["laplace_compile_wall"] = Figure("speed_compile.json", "compilation.wall_s", "{:.0f} s")
FIGURES["laplace_compile_load"] = Figure("speed_compile.json", "meta.load_average_at_start.0", "{:.1f}")
FIGURES["laplace_compile_load_end"] = Figure("speed_compile.json", "meta.load_average_at_end.0", "{:.1f}")
_MIX = "mixed_lengthscale.json"
# (a dotted key cannot name the sigma_R = 0.1 arms: the page reads them from the table)
for _arm, _a in (("mixed, sigma_R = 1", "mixed1"), ("ratings only", "ratings")):
    for _i in (0, 1):
        FIGURES[f"laplace_mix_{_a}_ls{_i}"] = Figure(_MIX, f"arms.{_arm}.lengthscale.{_i}", "{:.3f}")
_M1 = "arms.mixed, sigma_R = 1"
FIGURES["laplace_mix_mixed1_ev"] = Figure(_MIX, f"{_M1}.evidence_with_priors", "{:.1f}")
FIGURES["laplace_mix_mixed1_evals"] = Figure(_MIX, f"{_M1}.lbfgs_evaluations")
FIGURES["laplace_mix_mixed1_cpu"] = Figure(_MIX, f"{_M1}.fit_cpu_s", "{:.1f} s")
FIGURES["laplace_large_f32"] = Figure(_LARGE, "resolve_factorisations.factorise_float32")
FIGURES["laplace_large_f64"] = Figure(_LARGE, "resolve_factorisations.factorise")
FIGURES["laplace_large_load"] = Figure(_LARGE, "load_average_at_start.0", "{:.1f}")
FIGURES["laplace_large_extrapolated"] = Figure(_LARGE, "extrapolated_evaluation_cpu_s", "{:.0f} s")
# docs/serve.md: the soak's remaining figures, the kills and the timing run
_SOAK = "serve/soak.json"
FIGURES["serve_soak_fds_after"] = Figure(_SOAK, "after_run.fds")
FIGURES["serve_soak_files_after"] = Figure(_SOAK, "after_run.session_files")
FIGURES["serve_soak_answers"] = Figure(_SOAK, "summary.answers_acknowledged_in_run", "{:,}")
FIGURES["serve_soak_other_p50"] = Figure(_SOAK, "summary.answer_ms_other_p50_p95_p99.0", "{:.0f}")
FIGURES["serve_soak_other_p99"] = Figure(_SOAK, "summary.answer_ms_other_p50_p95_p99.2", "{:.0f}")
FIGURES["serve_soak_plots_n"] = Figure(_SOAK, "summary.answer_ms_during_plots_p50_p95_p99_n.3")
_KILL = "serve/kill.json"
for _key in ("kills", "acknowledged", "answers_in_file", "lost_count", "server_starts"):
    FIGURES[f"serve_kill_{_key}"] = Figure(_KILL, _key)
for _key, _k in (
    ("acknowledged before the kill", "before"),
    ("recorded on retry", "retry"),
    ("already recorded on retry", "duplicate"),
):
    FIGURES[f"serve_kill_{_k}"] = Figure(_KILL, f"outcomes.{_key}")
FIGURES["serve_kill_partial"] = Figure(_KILL, "partial_lines_repaired")
FIGURES["serve_kill_load_before"] = Figure(_KILL, "load_average_before.0", "{:.1f}")
FIGURES["serve_kill_load_after"] = Figure(_KILL, "load_average_after.0", "{:.1f}")
_TIMING = "serve/timing.json"
FIGURES["serve_timing_records"] = Figure(_TIMING, "summary.records_with_response_time")
FIGURES["serve_timing_answers"] = Figure(_TIMING, "summary.answers")
FIGURES["serve_timing_target"] = Figure(_TIMING, "summary.target_median_server_ms", "{:.0f} ms")
FIGURES["serve_timing_met"] = Figure(_TIMING, "summary.target_met")
FIGURES["serve_timing_load_before"] = Figure(_TIMING, "summary.load_average_before.0", "{:.1f}")
FIGURES["serve_timing_load_after"] = Figure(_TIMING, "summary.load_average_after.0", "{:.1f}")
# docs/sessions.md: the scale table (one figure a cell), its loads and target, and the kills
_SCALE_JSON = "sessions/session_scale.json"
for _a in (10, 100, 1000, 5000):
    for _op in ("answer", "undo", "resume", "resume_cold", "ask"):
        FIGURES[f"sessions_this_{_op}_{_a}"] = Figure(_SCALE, f"seconds@answers={_a},code=this,operation={_op}", "ms")
    if _a <= 1000:
        FIGURES[f"sessions_previous_answer_{_a}"] = Figure(
            _SCALE, f"seconds@answers={_a},code=previous (replay),operation=answer", "ms"
        )
        for _op in ("undo", "resume"):
            FIGURES[f"sessions_previous_{_op}_{_a}"] = Figure(
                _SCALE, f"seconds@answers={_a},code=previous (replay),operation={_op}", "{:.2f} s"
            )
FIGURES["sessions_scale_load_before"] = Figure(_SCALE_JSON, "load_average_before.0", "{:.1f}")
FIGURES["sessions_scale_load_after"] = Figure(_SCALE_JSON, "load_average_after.0", "{:.1f}")
FIGURES["sessions_scale_target_met"] = Figure(_SCALE_JSON, "target_under_50_ms")
_SKILLS = "sessions/session_kills.json"
for _key in (
    "files_checked",
    "acknowledged_answers",
    "acknowledged_undos",
    "lost",
    "doubled",
    "undos_lost",
    "all_sequences_ok",
    "open_failures",
):
    FIGURES[f"sessions_kills_{_key}"] = Figure(_SKILLS, _key)
FIGURES["sessions_kills_posterior"] = Figure(_SKILLS, "max_posterior_vs_replay", "sci")
# docs/study.md: the runs' loads, the runs without and with kills side by side
FIGURES["study_run_lost"] = Figure("study/study_run.json", "lost", "{}")
FIGURES["study_run_load_start"] = Figure("study/study_run.json", "load_average_start_end.0", "{:.1f}")
FIGURES["study_kill_load_start"] = Figure("study/study_run_kills.json", "load_average_start_end.0", "{:.1f}")
FIGURES["study_kill_per5"] = Figure("study/study_run_kills.json", "refits_per_5_finished", "{:.2f}")
# --- results.md, lake.md, README (issue 53): the bare numbers of these pages (means ± s.e., verdict
# cell counts, paired differences, largest p of a family) taken off hand-typed prose


@dataclass(frozen=True)
class Extreme(Figure):
    """The largest (``pick="max"``) or smallest of several keys of one file, ``key`` being the dotted
    keys joined by ``|``: a page writes "largest p ..." over a family of tests without naming the
    test that is largest in this run."""

    pick: str = "max"

    def raw(self) -> float | int | str:
        values = [Figure(self.file, k).raw() for k in self.key.split("|")]
        return max(values) if self.pick == "max" else min(values)


@dataclass(frozen=True)
class Cells(Figure):
    """How many of a suite summary's verdict cells (family/condition, checkpoint, metric) a strategy is
    best or tied in: ``key`` is ``strategy|checkpoint kind|metric`` ("queries" or "effort"; an empty
    part matches every one), strategy ``*`` counts the cells themselves."""

    def raw(self) -> int:
        strategy, kind, metric = self.key.split("|")
        data = load(self.file)
        if strategy == "*":
            cells = [(cp, m) for by_cp in data["verdicts"].values() for cp, by_m in by_cp.items() for m in by_m]
        else:
            cells = [(cp, m) for _, _, cp, m, s in _cells(data) if s == strategy]
        return sum(kind in ("", cp.split()[0]) and metric in ("", m) for cp, m in cells)


_RSEL, _RCLIP = "lakes10_selector/lake_summary.json", "lakes10_selector_clipped/lake_summary.json"
_RSUITE = "suite50/suite_summary.json"
_SUITE_STRATEGIES = (
    ("UCBC", "ucbc"),
    ("random ratings", "random"),
    ("random rankings", "rankings"),
    ("UCB ratings", "ucb"),
    ("info per effort", "info"),
    ("top & level info", "toplevel"),
    ("variance per effort", "variance"),
    ("profile per effort", "profile"),
    ("clipped profile", "clipped"),
)
# docs/results.md: the wave's table at 20 queries in words (wave_summary.json) and profile per effort on
# the same trials (wave_selector/)
for _s, _n in (
    ("UCBC", "ucbc"),
    ("random rankings", "rankings"),
    ("UCB ratings", "ucb"),
    ("random ratings", "random"),
    ("info per effort", "info"),
):
    if _n not in ("ucbc", "info"):  # their means: wave_wrms_ucbc, wave_tp_info, ...
        FIGURES[f"results_wave_wrms_{_n}"] = Figure(_WAVE, f"final.{_s}.wrms.0", "{:.4f}")
        FIGURES[f"results_wave_tp_{_n}"] = Figure(_WAVE, f"final.{_s}.tp.0", "{:.2f}")
    FIGURES[f"results_wave_wrms_se_{_n}"] = Figure(_WAVE, f"final.{_s}.wrms.1", "{:.4f}")
    FIGURES[f"results_wave_tp_se_{_n}"] = Figure(_WAVE, f"final.{_s}.tp.1", "{:.2f}")
for _s, _n in (("profile per effort", "profile"), ("info per effort", "info")):
    FIGURES[f"results_wsel_wrms_{_n}"] = Figure(_WSEL, f"final.{_s}.wrms.0", "{:.4f}")
    FIGURES[f"results_wsel_wrms_se_{_n}"] = Figure(_WSEL, f"final.{_s}.wrms.1", "{:.4f}")
    FIGURES[f"results_wsel_tp_{_n}"] = Figure(_WSEL, f"final.{_s}.tp.0", "{:.2f}")
    FIGURES[f"results_wsel_tp_se_{_n}"] = Figure(_WSEL, f"final.{_s}.tp.1", "{:.2f}")
FIGURES["results_wsel_p_info_profile_tp"] = Figure(
    _WSEL, f"{_Q}.info per effort vs profile per effort.tp.p_wilcoxon", "{:.2f}"
)
# docs/results.md: the one lake's final errors, the 10-lake shares and planning, the 20-lake planning
FIGURES["results_lakes10_plan_worse"] = Figure(_RSEL, "planning.UCBC.worse")
FIGURES["results_lakes20_plan_worse"] = Figure(_L20, "planning.UCBC.worse")
# docs/results.md: the 9-strategy suite (suite50/): its time summed over its runs, its verdict cells
FIGURES["results_suite50_wall"] = Figure(_RSUITE, "wall_time_s", "{:,.0f} s")
FIGURES["results_suite50_cpu"] = Figure(_RSUITE, "cpu_time_s", "{:,.0f} s")
FIGURES["results_suite50_cells"] = Cells(_RSUITE, "*||")
for _kind in ("queries", "effort"):
    FIGURES[f"results_suite50_cells_{_kind}"] = Cells(_RSUITE, f"*|{_kind}|")
FIGURES["results_suite50_cells_metric"] = Cells(_RSUITE, "*||wrms")
for _s, _n in _SUITE_STRATEGIES:
    FIGURES[f"results_suite50_best_{_n}"] = Figure(_RSUITE, f"best_or_tied.{_s}.0")
for _s, _n, _part in (
    ("profile per effort", "profile", "queries|"),
    ("profile per effort", "profile", "|tp"),
    ("profile per effort", "profile", "|regret"),
    ("profile per effort", "profile", "|wrms"),
    ("clipped profile", "clipped", "effort|"),
    ("clipped profile", "clipped", "|wrms"),
):
    FIGURES[f"results_suite50_best_{_n}_{_part.strip('|')}"] = Cells(_RSUITE, f"{_s}|{_part}")
for _s, _n in (("profile per effort", "profile"), ("UCB ratings", "ucb")):
    FIGURES[f"results_suite50_plateau_wrms_{_n}"] = Figure(
        _RSUITE, f"verdicts.plateau/fixed.queries 20.wrms.mean.{_s}", "{:.3f}"
    )
# README: the most cells any one strategy of the suite is best or tied in
FIGURES["readme_suite50_most_cells"] = Extreme(
    _RSUITE, "|".join(f"best_or_tied.{_s}.0" for _s, _ in _SUITE_STRATEGIES), "{}"
)
# docs/results.md: the person calibration (person_calibration.json) and the realistic suite at equal
# seconds (suite_realistic_plain/, suite_realistic_trajectories/)
FIGURES["results_realistic_cells"] = Cells("suite_realistic_plain/suite_summary.json", "*|effort|")
for _effort in ("plain", "trajectories"):
    _file = f"suite_realistic_{_effort}/suite_summary.json"
    for _s, _n in (
        ("UCBC", "ucbc"),
        ("clipped profile", "clipped"),
        ("profile per second", "second"),
        ("UCB ratings", "ucb"),
    ):
        FIGURES[f"results_realistic_{_effort}_{_n}"] = Cells(_file, f"{_s}|effort|")
# docs/results.md: ties and Likert levels (ordinal.json)
_RT = "summary.ties"
_RL = "summary.likert"
_TIE_SETTINGS = (("wave 10%", "w10"), ("wave 25%", "w25"), ("bump 10%", "b10"), ("bump 25%", "b25"))
for _setting, _n in _TIE_SETTINGS[:2]:
    for _arm in ("ignored", "used"):
        FIGURES[f"results_ties_{_n}_{_arm}_wrms"] = Figure(_ORD, f"{_RT}.{_setting}.{_arm}/wrms.0", "{:.4f}")
    FIGURES[f"results_ties_{_n}_tau_learned"] = Figure(_ORD, f"{_RT}.{_setting}.tau_learned_mean", "{:.2f}")
    FIGURES[f"results_ties_{_n}_margin"] = Figure(_ORD, f"{_RT}.{_setting}.margin_mean", "{:.2f}")
for _arm, _metrics in (
    ("used", (("tp", "{:+.2f}"), ("regret", "{:+.3f}"))),
    ("default", (("wrms", "{:+.4f}"), ("tp", "{:+.2f}"), ("regret", "{:+.3f}"))),
    ("learned", (("wrms", "{:+.4f}"), ("tp", "{:+.2f}"))),
):
    for _setting, _n in _TIE_SETTINGS:
        for _m, _fmt in _metrics:
            FIGURES[f"results_ties_{_n}_{_arm}_{_m}"] = Figure(
                _ORD, f"{_RT}.{_setting}.{_arm} - ignored/{_m}.mean_diff", _fmt
            )
FIGURES["results_ties_p_b10_used_regret"] = Figure(_ORD, f"{_RT}.bump 10%.used - ignored/regret.p_ttest", "{:.2f}")
for _arm, _metrics, _settings in (
    ("used", ("wrms",), _TIE_SETTINGS),
    ("used", ("tp",), _TIE_SETTINGS),
    ("used", ("regret",), _TIE_SETTINGS[:2]),
    ("default", ("wrms", "tp", "regret"), _TIE_SETTINGS),
):
    FIGURES[f"results_ties_p_max_{_arm}_{'_'.join(_metrics)}_{len(_settings)}"] = Extreme(
        _ORD,
        "|".join(f"{_RT}.{_s}.{_arm} - ignored/{_m}.p_ttest" for _s, _ in _settings for _m in _metrics),
        "{:.2g}",
    )
for _arm in ("beta", "ordinal"):
    FIGURES[f"results_likert_wave_{_arm}_wrms"] = Figure(_ORD, f"{_RL}.wave.{_arm}/wrms.0", "{:.4f}")
FIGURES["results_likert_lake_tp"] = Figure(_ORD, f"{_RL}.lake.ordinal - beta/tp.mean_diff", "{:+.2f}")
FIGURES["results_likert_p_min_other"] = Extreme(
    _ORD,
    "|".join(
        f"{_RL}.{_u}.ordinal - beta/{_m}.p_ttest"
        for _u in ("wave", "partial", "bump", "lake")
        for _m in ("tp", "regret")
        if (_u, _m) != ("lake", "tp")
    ),
    "{:.2f}",
    pick="min",
)
FIGURES["results_likert_learned_lake_wrms"] = Figure(
    _ORD, f"{_RL}.lake.ordinal-learned - beta/wrms.mean_diff", "{:+.4f}"
)
FIGURES["results_likert_learned_lake_p_wrms"] = Figure(_ORD, f"{_RL}.lake.ordinal-learned - beta/wrms.p_ttest", "sci")
FIGURES["results_likert_learned_lake_tp"] = Figure(_ORD, f"{_RL}.lake.ordinal-learned - beta/tp.mean_diff", "{:+.2f}")
# docs/lake.md: the one-lake run's table, its first query, its paired differences (lake_summary.json)
for _s, _n in (("UCBC", "ucbc"), ("random ratings", "random"), ("UCB ratings", "ucb"), ("info per effort", "info")):
    for _m in ("error5", "wrms"):
        FIGURES[f"lake_one_{_m}_{_n}"] = Figure(_L1, f"final.{_s}.{_m}.0", "{:.3f}")
        FIGURES[f"lake_one_{_m}_se_{_n}"] = Figure(_L1, f"final.{_s}.{_m}.1", "{:.3f}")
    FIGURES[f"lake_one_chosen_{_n}"] = Figure(_L1, f"final.{_s}.chosen_rating.0", "{:.2f}")
    FIGURES[f"lake_one_rated5_{_n}"] = Figure(_L1, f"share_rated_5.{_s}", "{:.2f}")
    FIGURES[f"lake_one_ratings_{_n}"] = Figure(_L1, f"fraction_ratings.{_s}", "{:.2f}")
for _m, _fmt in (("error5", "{:.3f}"), ("wrms", "{:.3f}"), ("chosen_rating", "{:.2f}")):
    FIGURES[f"lake_one_start_{_m}"] = Figure(_L1, f"per_query.UCBC.{_m}_mean.0", _fmt)
FIGURES["lake_one_test_rated5"] = Figure(_L1, "settings.test_paths_rated_5.0")
for _pair, _n in (
    ("UCBC vs random ratings", "random"),
    ("UCBC vs UCB ratings", "ucb"),
    ("UCBC vs info per effort", "info"),
):
    for _m in ("error5", "wrms"):
        FIGURES[f"lake_diff_{_n}_{_m}"] = Figure(_L1, f"paired_tests.{_pair}.{_m}.mean_diff", "{:+.3f}")
# docs/lake.md: the 10-lake planning run (lakes/) and the 20-lake one (lakes20/)
FIGURES["lake_many_worse"] = Figure(_L10, "planning.UCBC.worse")
FIGURES["lake_many_gain_mean"] = Figure(_L10, "planning.UCBC.distance_gain.mean", "{:.1f}")
FIGURES["lake_many_gain_max"] = Figure(_L10, "planning.UCBC.distance_gain.max", "{:.0f}")
FIGURES["lake_many_fallback"] = Figure(_L10, "planning.UCBC.sources.fallback")
FIGURES["lake_many_planned"] = Figure(_L10, "planning.UCBC.sources.planned")
for _r in ("wins", "losses", "ties"):
    FIGURES[f"lake_many_levels_{_r}"] = Figure(_L10, f"planning.UCBC.paired.{_r}")
for _r in ("planned", "pick"):
    FIGURES[f"lake_many_{_r}_level"] = Figure(_L10, f"planning.UCBC.{_r}_level_mean", "{:.3f}")
for _s, _n in (("UCBC", "ucbc"), ("random ratings", "random"), ("UCB ratings", "ucb"), ("info per effort", "info")):
    FIGURES[f"lake_many_error5_{_n}"] = Figure(_L10, f"final.{_s}.error5.0", "{:.3f}")
    FIGURES[f"lake_many_error5_se_{_n}"] = Figure(_L10, f"final.{_s}.error5.1", "{:.3f}")
    FIGURES[f"lake_many_rated5_{_n}"] = Figure(_L10, f"share_rated_5.{_s}", "{:.3g}")
TABLES["lake_plan_per_lake_20"] = Table(_L20, TABLES["lake_plan_per_lake"].columns, rows="per_lake")
# --- end of results.md, lake.md, README (issue 53)

# audit (issue 53)
_FZ = "fuzz.json"
FIGURES["audit_fuzz_f32n_exceptions"] = Figure(_FZ, "f32n.exceptions")
FIGURES["audit_fuzz_comp_problems"] = Figure(_FZ, "comparisons_only.problems", "{:,}")
FIGURES["audit_fuzz_comp_f64"] = Figure(_FZ, "comparisons_only.f64_exceptions")
FIGURES["audit_fuzz_comp_f32"] = Figure(_FZ, "comparisons_only.f32_exceptions")
FIGURES["audit_fuzz_comp_f32n"] = Figure(_FZ, "comparisons_only.f32n_exceptions")
FIGURES["audit_fuzz_comp_pairwisegp"] = Figure(_FZ, "comparisons_only.pairwisegp_f32_exceptions")
for _r in ("f64", "f32", "f32n"):
    FIGURES[f"audit_fuzz_{_r}_nan"] = Figure(_FZ, f"{_r}.nan")
    FIGURES[f"audit_fuzz_{_r}_unconverged"] = Figure(_FZ, f"{_r}.unconverged")
for _r in ("f32", "f32n"):
    for _g in ("nograd", "grad"):
        FIGURES[f"audit_fuzz_{_r}_{_g}_within"] = Figure(_FZ, f"agreement_{_r}_{_g}.within_target", "{:,}")
    FIGURES[f"audit_fuzz_{_r}_agree_problems"] = Figure(_FZ, f"agreement_{_r}_nograd.problems", "{:,}")
    FIGURES[f"audit_fuzz_{_r}_median_gap"] = Figure(_FZ, f"agreement_{_r}_nograd.median", "sci")
    FIGURES[f"audit_fuzz_{_r}_max_gap"] = Figure(_FZ, f"agreement_{_r}_nograd.max", "sci")
FIGURES["audit_fuzz_f32n_max_gap_2"] = Figure(_FZ, "agreement_f32n_nograd.max", "{:.2f}")
FIGURES["audit_fuzz_f32n_jitter_beyond"] = Figure(_FZ, "f32n_beyond_target_with_jitter_at_least_1e-5")


@dataclass(frozen=True)
class _Minus(Figure):
    """The value at the first of the ``|``-joined keys less those at the others."""

    def raw(self) -> float | int:
        first, *rest = (Figure(self.file, k).raw() for k in self.key.split("|"))
        return first - sum(rest)


def _fuzz_native(key: str) -> Any:
    """What fuzz.csv says of native float32's problems beyond the agreement target: ``key`` is
    ``long`` (those with jitter of 1e-5 or more at lengthscales above 20), ``short_min`` /
    ``short_max`` (the others' lengthscales), ``rounding_max`` (the largest gap of those with less
    jitter), ``rounding_seeds`` (theirs above 0.05), ``kernel_errors`` (exceptions of the kernel
    matrix), ``fisher_seeds`` (those of the Fisher-scoring matrix)."""
    rows = load("fuzz.csv")
    target = load("fuzz.json")["target"]

    def gap(r: dict) -> float:
        return max(float(r["f32n_gap_mean_nograd"]), float(r["f32n_gap_cov_nograd"]))

    beyond = [r for r in rows if not r["f32n_error"] and r["f32n_gap_mean_nograd"] and gap(r) > target]
    jitter = [r for r in beyond if float(r["f32n_jitter"] or 0) >= 1e-5]
    short = [float(r["lengthscale"]) for r in jitter if float(r["lengthscale"]) <= 20]
    rounding = [r for r in beyond if float(r["f32n_jitter"] or 0) < 1e-5]
    errors = [r for r in rows if r["f32n_error"]]
    return {
        "long": len(jitter) - len(short),
        "short_min": min(short),
        "short_max": max(short),
        "rounding_max": max(gap(r) for r in rounding),
        "rounding_seeds": ", ".join(sorted((r["seed"] for r in rounding if gap(r) > 0.05), key=int)),
        "kernel_errors": sum("kernel matrix" in r["f32n_error"] for r in errors),
        "fisher_seeds": " and ".join(r["seed"] for r in errors if "Fisher" in r["f32n_error"]),
    }[key]


@dataclass(frozen=True)
class _FuzzNative(Figure):
    def raw(self) -> Any:
        return _fuzz_native(self.key)


_F32N = "agreement_f32n_nograd"
FIGURES["audit_fuzz_f32n_beyond"] = _Minus(_FZ, f"{_F32N}.problems|{_F32N}.within_target")
FIGURES["audit_fuzz_f32n_rounding"] = _Minus(
    _FZ, f"{_F32N}.problems|{_F32N}.within_target|f32n_beyond_target_with_jitter_at_least_1e-5"
)
for _k, _f in (
    ("long", "{}"),
    ("short_min", "{:.2f}"),
    ("short_max", "{:.0f}"),
    ("rounding_max", "{:.2f}"),
    ("rounding_seeds", "{}"),
    ("kernel_errors", "{}"),
    ("fisher_seeds", "{}"),
):
    FIGURES[f"audit_fuzz_native_{_k}"] = _FuzzNative("fuzz.csv", _k, _f)


for _i in range(5):  # native float32's largest gaps from float64 (the file's worst five, largest first)
    _w = f"agreement_f32n_nograd.worst.{_i}"
    FIGURES[f"audit_fuzz_worst{_i}_seed"] = Figure(_FZ, f"{_w}.seed")
    FIGURES[f"audit_fuzz_worst{_i}_gap"] = Figure(_FZ, f"{_w}.gap", "{:.2f}")
    FIGURES[f"audit_fuzz_worst{_i}_ls"] = Figure(_FZ, f"{_w}.lengthscale", "{:.0f}")
# docs/likelihoods.md: the person calibration's recovery table and paired means
for _p in ("rating_offset", "rating_gain", "lapse_rate", "rating_precision"):
    for _c in ("rmse", "prior_rmse", "correlation"):
        FIGURES[f"pcal_{_p}_{_c}"] = Figure(_PCAL, f"recovery.{_p}.{_c}", "{:.2f}")
    FIGURES[f"pcal_{_p}_bias"] = Figure(_PCAL, f"recovery.{_p}.bias", "{:+.2f}")
FIGURES["pcal_lapse_under"] = Figure(_PCAL, "recovery.lapse_rate.bias", "{:.2f}")
for _m, _f in (("wrms", "{:.3f}"), ("tp", "{:.2f}"), ("regret", "{:.3f}")):
    for _arm in ("calibrated", "plain"):
        FIGURES[f"pcal_{_m}_{_arm}"] = Figure(_PCAL, f"recovery.paired.{_m}.{_arm}", _f)
        FIGURES[f"pcal_ideal_{_m}_{_arm}"] = Figure(_PCAL, f"ideal.{_m}.{_arm}", "{:.4f}" if _m == "wrms" else _f)
FIGURES["pcal_load"] = Figure(_PCAL, "stamp.load_avg.0", "{:.1f}")


# docs/wave.md: the paired differences at 20 queries (wave_summary.json's paired_tests.queries)
def _p_text(p: float) -> str:
    return formatted(p, "sci") if p < 0.001 else f"{p:.2g}"


def _wave_paired_rows(summary: dict) -> list[dict]:
    order = (
        "UCBC vs random ratings",
        "UCBC vs random rankings",
        "UCBC vs UCB ratings",
        "info per effort vs UCBC",
        "info per effort vs random rankings",
        "info per effort vs UCB ratings",
        "info per effort vs random ratings",
    )
    out = []
    for pair in order:
        t = summary["paired_tests"]["queries"][pair]
        w, tp = t["wrms"], t["tp"]
        out.append(
            {
                "comparison": pair.replace("info per effort", "info").replace(" vs ", " − "),
                "dwrms": f"{w['mean_diff']:+.4f} ± {w['sem_diff']:.4f}".replace("-", "−").lstrip("+"),
                "pwrms": f"{_p_text(w['p_wilcoxon'])} / {_p_text(w['p_ttest'])}",
                "dtp": f"{tp['mean_diff']:+.2f} ± {tp['sem_diff']:.2f}".replace("-", "−"),
                "ptp": f"{_p_text(tp['p_wilcoxon'])} / {_p_text(tp['p_ttest'])}",
            }
        )
    return out


# docs/wave.md: the strategies at an effort of 20 and the paired differences there and at 20 queries
for _s, _n in (
    ("UCBC", "ucbc"),
    ("random ratings", "random_ratings"),
    ("random rankings", "random_rankings"),
    ("UCB ratings", "ucb"),
    ("info per effort", "info"),
):
    FIGURES[f"audit_wave_effort_wrms_{_n}"] = Figure(_WAVE, f"per_effort.{_s}.wrms_mean.20", "{:.4f}")
    FIGURES[f"audit_wave_effort_wrms_se_{_n}"] = Figure(_WAVE, f"per_effort.{_s}.wrms_sem.20", "{:.4f}")
    FIGURES[f"audit_wave_effort_tp_{_n}"] = Figure(_WAVE, f"per_effort.{_s}.tp_mean.20", "{:.2f}")
    FIGURES[f"audit_wave_effort_tp_se_{_n}"] = Figure(_WAVE, f"per_effort.{_s}.tp_sem.20", "{:.2f}")
for _pair, _m, _n, _f in (
    ("info per effort vs UCBC", "wrms", "info_ucbc_wrms", "{:+.4f}"),
    ("info per effort vs UCBC", "tp", "info_ucbc_tp", "{:+.2f}"),
    ("info per effort vs random rankings", "tp", "info_rankings_tp", "{:+.2f}"),
    ("UCBC vs UCB ratings", "wrms", "ucbc_ucb_wrms", "{:+.4f}"),
):
    FIGURES[f"audit_wave_effort_diff_{_n}"] = Figure(_WAVE, f"paired_tests.effort.{_pair}.{_m}.mean_diff", _f)
for _pair, _m, _n, _f in (
    ("UCBC vs random rankings", "tp", "ucbc_rankings_tp", "{:+.2f}"),
    ("info per effort vs UCBC", "wrms", "info_ucbc_wrms", "{:+.4f}"),
    ("info per effort vs UCBC", "tp", "info_ucbc_tp", "{:+.2f}"),
    ("info per effort vs random rankings", "tp", "info_rankings_tp", "{:+.2f}"),
):
    FIGURES[f"audit_wave_diff_{_n}"] = Figure(_WAVE, f"paired_tests.queries.{_pair}.{_m}.mean_diff", _f)
FIGURES["audit_wave_proc_load_start"] = Figure(_WPROC, "load_average_at_start.0", "{:.0f}")
FIGURES["audit_wave_proc_load_end"] = Figure(_WPROC, "load_average_at_end.0", "{:.0f}")


# docs/ax.md: Ax's own tests, the table of the documented path, Ax as it is and the harness
@dataclass(frozen=True)
class _Count(Figure):
    """How many entries the list at ``key`` holds."""

    def raw(self) -> int:
        return len(super().raw())


_AXU = "ax/upstream_tests.json"
FIGURES["audit_ax_upstream_files"] = _Count(_AXU, "files")
for _mode in ("documented", "plain", "harness"):
    for _c in ("ran", "passed", "fit_a_preference_model", "fit_and_passed"):
        FIGURES[f"audit_ax_{_mode}_{_c}"] = Figure(_AXU, f"modes.{_mode}.counts.{_c}")
    for _c in ("built_preference_gp_only", "built_pairwise_gp_only", "built_both"):
        FIGURES[f"audit_ax_{_mode}_{_c}"] = _Count(_AXU, f"modes.{_mode}.counts.{_c}")
    FIGURES[f"audit_ax_{_mode}_load"] = Figure(_AXU, f"modes.{_mode}.load_average_at_start", "{:.1f}")
# docs/population.md: the shard rows' load averages, lowest and highest
_SHARD_LOADS = "|".join(f"rows.{_i}.load_start_end.{_j}" for _i in range(6) for _j in range(2))
FIGURES["audit_shards_load_lo"] = Extreme(_SHARDS, _SHARD_LOADS, "{:.1f}", pick="min")
FIGURES["audit_shards_load_hi"] = Extreme(_SHARDS, _SHARD_LOADS, "{:.1f}", pick="max")

TABLES["audit_wave_paired"] = Table(
    "wave_summary.json",
    (
        ("comparison", "comparison", "{}"),
        ("ΔWRMS", "dwrms", "{}"),
        ("p", "pwrms", "{}"),
        ("ΔTP", "dtp", "{}"),
        ("p", "ptp", "{}"),
    ),
    rows=_wave_paired_rows,
)
# docs/robustness.md: the hostile-start fits' outcomes (hostile_fits.json)
_HF = "hostile_fits.json"
FIGURES["audit_hostile_fits"] = Figure(_HF, "fits")
FIGURES["audit_hostile_fit"] = Figure(_HF, "counts.fit")
FIGURES["audit_hostile_other"] = Figure(_HF, "other")
FIGURES["audit_hostile_unconverged"] = Figure(_HF, "counts.unusable: mode not converged")
FIGURES["audit_hostile_98_seed"] = Figure(_HF, "rows.98.seed")
FIGURES["audit_hostile_98_n"] = Figure(_HF, "rows.98.n")
FIGURES["audit_hostile_98_seconds"] = Figure(_HF, "rows.98.seconds", "{:.0f} s")
FIGURES["audit_hostile_4_seconds"] = Figure(_HF, "rows.4.seconds", "{:.0f} s")
FIGURES["audit_hostile_load"] = Figure(_HF, "stamp.load_avg.0", "{:.1f}")
# docs/likelihoods.md: the ties' gain in true positives, smallest and largest (ordinal.json)
FIGURES["audit_ord_ties_tp_min"] = Figure(_ORD, "summary.ties.bump 10%.used - ignored/tp.mean_diff", "{:.1f}")
FIGURES["audit_ord_ties_tp_max"] = Figure(_ORD, "summary.ties.wave 10%.used - ignored/tp.mean_diff", "{:.1f}")
# docs/botorch.md: the ported API checks' table
FIGURES["audit_api_pairwisegp_failed"] = Figure("botorch_api_counts.json", "summary.PairwiseGP.failed")
# docs/speed.md: the first call, re-measured on the current code
_FC = "fast_path/first_call.json"
for _arm, _n in (("off", "off"), ("auto, cache on disk", "auto")):
    FIGURES[f"audit_first_call_{_n}_imports"] = Figure(_FC, f"rows.{_arm}.imports_s", "{:.1f} s")
    FIGURES[f"audit_first_call_{_n}_first_cpu"] = Figure(_FC, f"rows.{_arm}.first_fit_cpu_s", "{:.3f} s")
FIGURES["audit_first_call_load"] = Figure(_FC, "stamp.load_avg.0", "{:.1f}")
FIGURES["audit_speedq_load_start_5"] = Figure(
    "speed_quiet/speed_pairwise.json", "meta.load_average_at_start.1", "{:.1f}"
)

SUBSTITUTION = re.compile(r"\{\{\s*(?P<name>\w+)\s*\}\}")


def is_stale(name: str) -> bool:
    """Whether the figure's (or table's) results file is stale (its measured code changed since its stamp)."""
    return file_state((FIGURES.get(name) or TABLES[name]).file) == "stale"


def file_state(file: str) -> str:
    """``"fresh"``, ``"stale"`` or ``"unstamped"`` (``make results-status``); a CSV is judged by the
    JSON of the same name beside it, and is ``"unstamped"`` without one."""
    path = ROOT / "benchmarks" / "results" / file
    if path.suffix != ".json":
        path = path.with_suffix(".json")
    return _state(path, ROOT) if path.is_file() else "unstamped"


@functools.cache
def _state(path: Path, root: Path) -> str:
    """A results file's state, judged once per process: many figures share a file, and judging it
    hashes every source its stamp lists (a page write or a test run changes no source)."""
    from torchpref.experiments.stamp import status

    return status(path, root)[0]


def note(name: str, table: bool = False) -> str:
    """The visible note a figure (or table) carries: stale, unstamped, or none when its file is fresh."""
    state = file_state((TABLES[name] if table else FIGURES[name]).file)
    if table:
        return {"stale": "\n\n" + TABLE_STALE_NOTE, "unstamped": "\n\n" + TABLE_UNSTAMPED_NOTE}.get(state, "")
    return {"stale": STALE_NOTE, "unstamped": UNSTAMPED_NOTE}.get(state, "")


def without_note(text: str) -> str:
    """A page's text of a figure or table with its note taken off."""
    for suffix in (STALE_NOTE, UNSTAMPED_NOTE, "\n\n" + TABLE_STALE_NOTE, "\n\n" + TABLE_UNSTAMPED_NOTE):
        text = text.removesuffix(suffix)
    return text


def substitutions() -> dict[str, str]:
    """``{name: text}`` for MyST, with each figure's :func:`note`."""
    return {name: page_text(name) for name in FIGURES}


PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def page_text(name: str) -> str:
    """What a page shows for figure ``name``: its value and its :func:`note` (stale, unstamped)."""
    return FIGURES[name].text() + note(name)


def table_text(name: str) -> str:
    """What a page shows for table ``name``: the table, then its :func:`note` (stale, unstamped)."""
    return TABLES[name].text() + note(name, table=True)


def write_pages(pages: list[Path] | None = None) -> dict[str, int]:
    """Write every figure and table into the pages (``make pages``): each ``{{ name }}`` becomes
    ``<!-- fig:name -->value<!-- /fig -->``, every marker's text is set to :func:`page_text` and
    every table's to :func:`table_text`, so a page read as a file (on GitHub, in an editor) shows the
    numbers. Returns ``{page: figures and tables}``."""
    out = {}
    texts: dict[str, str] = {}

    def text(name: str) -> str:
        if name not in texts:
            texts[name] = page_text(name)
        return texts[name]

    for page in pages or PAGES:
        old = page.read_text()
        new = SUBSTITUTION.sub(lambda m: f"<!-- fig:{m['name']} -->{text(m['name'])}<!-- /fig -->", old)
        new = MARKER.sub(lambda m: f"<!-- fig:{m['name']} -->{text(m['name'])}<!-- /fig -->", new)
        new = TABLE_MARKER.sub(lambda m: f"<!-- table:{m['name']} -->\n{table_text(m['name'])}\n<!-- /table -->", new)
        if new != old:
            page.write_text(new)
        out[page.relative_to(ROOT).as_posix()] = len(MARKER.findall(new)) + len(TABLE_MARKER.findall(new))
    return out


if __name__ == "__main__":
    import sys

    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python docs/figures.py --write   (writes every figure into README.md and docs/*.md)")
    for page, n in write_pages().items():
        if n:
            print(f"{page}: {n} figures")
