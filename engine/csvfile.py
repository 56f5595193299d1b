"""CSV files the user brings (2D traces, ground-control points): rows as dicts, or a clear error."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

from engine.errors import InputError


def read_csv(path: str | Path, columns: Sequence[str]) -> list[dict[str, str]]:
    """The rows of a CSV with a header holding at least `columns` (a BOM is allowed: spreadsheets write one).

    Raises InputError naming the file when it cannot be read or a column is missing. Row k of the result
    is line k + 2 of the file.
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, f"cannot read CSV ({exc})") from exc
    missing = [c for c in columns if c not in header]
    if missing:
        raise InputError(path, f"missing column(s) {', '.join(missing)}; expected {','.join(columns)}")
    return rows
