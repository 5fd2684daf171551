"""CSV tables written atomically (the project's one CSV writer)."""

from __future__ import annotations

import csv
import io
from pathlib import Path

from drake_rus.io_utils import write_text_atomic


def write_csv_atomic(
    path,
    rows: list[dict],
    fieldnames: list[str] | None = None,
    *,
    float_format: str | None = ".6g",
    extrasaction: str = "raise",
) -> Path:
    """Writes ``rows`` (dicts) as CSV to ``path``, atomically; returns the path.

    ``fieldnames``: the columns, in order (default: the first row's keys; no rows and no
    ``fieldnames`` gives an empty file). A row missing a column leaves it empty; a key not
    among the columns raises, or is dropped with ``extrasaction="ignore"``.
    ``float_format``: format spec of float cells (default ``.6g``; None writes ``str``).
    """
    buf = io.StringIO()
    if fieldnames is None and rows:
        fieldnames = list(rows[0])
    if fieldnames is not None:
        w = csv.DictWriter(buf, fieldnames=list(fieldnames), extrasaction=extrasaction)
        w.writeheader()
        for r in rows:
            if float_format is not None:
                r = {
                    k: (format(v, float_format) if isinstance(v, float) else v)
                    for k, v in r.items()
                }
            w.writerow(r)
    return write_text_atomic(path, buf.getvalue())
