"""What the pair and the video evaluation share: the detectors they run (names parsed,
extractors built from the registry) and their outputs' formats: plain-text tables, CSV and JSON
(nan and inf written so a reader gets them back) and matplotlib on the Agg backend.
"""

from __future__ import annotations

import csv
import io
import logging
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mosaic.config import Config, with_overrides
from mosaic.errors import ConfigError, DetectorWeightsError
from mosaic.features import DETECTORS, FeatureExtractor
from mosaic.io import write_text

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Detectors
# --------------------------------------------------------------------------------------------


def parse_detectors(spec: str | None) -> list[str]:
    """Detector names from "a,b,c" (None or "all": every detector of the registry)."""
    if spec is None or spec.strip() in ("", "all"):
        return list(DETECTORS)
    names = [s.strip() for s in spec.split(",") if s.strip()]
    unknown = [n for n in names if n not in DETECTORS]
    if unknown:
        raise ConfigError(
            f"unknown detector {', '.join(unknown)} (choices: {', '.join(DETECTORS)})"
        )
    return list(dict.fromkeys(names))


def make_extractors(
    config: Config, names: Sequence[str], explicit: bool = True
) -> dict[str, tuple[Config, FeatureExtractor]]:
    """One (config, extractor) per detector; glampoints is skipped (warning) without weights.

    With `explicit` False (the default list of every detector), detectors that the configured
    descriptor does not support are skipped with a warning instead of raising.
    """
    built: dict[str, tuple[Config, FeatureExtractor]] = {}
    for name in names:
        cfg = with_overrides(config, features={"detector": name})
        try:
            built[name] = (cfg, FeatureExtractor(cfg.features))
        except DetectorWeightsError as exc:
            log.warning("skipping detector %s: %s", name, exc)
        except ConfigError as exc:
            if explicit:
                raise
            log.warning("skipping detector %s: %s", name, exc)
    if not built:
        raise ConfigError(f"none of the detectors {', '.join(names)} can run")
    return built


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


def nanmean(values: Iterable[float]) -> float:
    """The mean of the finite values (nan when there are none)."""
    arr = np.asarray(list(values), dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    return float(arr.mean()) if arr.size else math.nan


def format_cell(value: Any, spec: str) -> str:
    """A table cell: `value` in format `spec`; "-" for none or nan, "inf" for infinities."""
    if isinstance(value, float) and not math.isfinite(value):
        return "-" if math.isnan(value) else "inf"
    if value is None:
        return "-"
    return format(value, spec) if spec else str(value)


def format_table(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]]) -> str:
    """Plain-text table: `columns` are (key, header, format spec); missing keys print "-"."""
    cells = [[header for _, header, _ in columns]]
    cells += [[format_cell(row.get(key), spec) for key, _, spec in columns] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(columns))]
    lines = [
        "  ".join(
            c.ljust(w) if i == 0 else c.rjust(w)
            for i, (c, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in cells
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Output files
# --------------------------------------------------------------------------------------------


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    """Rows of dicts as CSV (columns: union of keys in first-seen order; nested values as JSON)."""
    columns = list(dict.fromkeys(k for row in rows for k in row))
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=columns, restval="")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _csv_value(v) for k, v in row.items()})
    return write_text(path, text.getvalue())  # atomic: readers never see half a table


def _csv_value(value: Any) -> Any:
    """A CSV cell: floats to 6 significant digits, nan empty, infinities "inf"."""
    if isinstance(value, float):
        return "" if math.isnan(value) else (f"{value:.6g}" if math.isfinite(value) else "inf")
    return value


def json_safe(value: Any) -> Any:
    """nan -> None and inf -> "inf", recursively (JSON has neither)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend (imported lazily: only plotting needs it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
