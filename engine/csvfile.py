"""CSV files the user brings (2D traces, ground-control points): rows as dicts, or a clear error."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from engine.errors import InputError


def read_csv(path: str | Path, columns: Sequence[str]) -> list[dict[str, str]]:
    """The rows of a CSV with a header holding at least `columns` (a BOM is allowed: spreadsheets write one).

    Raises InputError naming the file when it cannot be read, a column is missing or a row has more fields
    than the header. Row k of the result is line k + 2 of the file.
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            rows = []
            for row in reader:
                if None in row:  # DictReader files the fields beyond the header under the key None
                    raise InputError(path, f"line {reader.line_num}: {len(header) + len(row[None])} fields, "
                                           f"expected {len(header)} as in the header ({','.join(header)})")
                rows.append(row)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, f"cannot read CSV ({exc})") from exc
    missing = [c for c in columns if c not in header]
    if missing:
        raise InputError(path, f"missing column(s) {', '.join(missing)}; expected {','.join(columns)}")
    if not rows:  # an import of nothing is a wrong file, not a result
        raise InputError(path, f"no rows below the header; expected one row per point ({','.join(columns)})")
    return rows


def csv_number(path: Path, line: int, column: str, text: str | None) -> float:
    """The finite number in a cell, or InputError naming the file, the line and the column."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise InputError(path, f"line {line}: column {column} is {text!r}, expected a number") from None
    if not np.isfinite(value):
        raise InputError(path, f"line {line}: column {column} is {text!r}, expected a finite number")
    return value
