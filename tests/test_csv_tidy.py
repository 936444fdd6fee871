"""Every CSV adnmesh writes loads in pandas with its default options: numeric columns are
numeric (no placeholder strings), one value per cell (a column per DER for subsets and
weights)."""

from __future__ import annotations

import csv
from pathlib import Path

import pandas as pd
from pandas.api.types import is_bool_dtype, is_numeric_dtype

from adnmesh.analysis.robustness import analyze_robustness
from adnmesh.tuning import write_csv
from coarse_table import example, small_table


def numeric(frame: pd.DataFrame, text: set[str]) -> None:
    """Every column but ``text`` is numeric or boolean."""
    for column in frame.columns:
        if column not in text:
            assert is_numeric_dtype(frame[column]) or is_bool_dtype(frame[column]), \
                (column, frame[column].dtype, frame[column].tolist()[:3])


def test_the_table_csv_is_tidy(tmp_path: Path) -> None:
    table = small_table("wt-chp")
    write_csv(table, tmp_path / "table.csv")
    frame = pd.read_csv(tmp_path / "table.csv")
    numeric(frame, {"subset", "reason", "tuned_by"})
    ders = list(table.der_ids)
    assert len(frame) == len(table.entries)
    for _, row in frame.iterrows():
        members = set(row["subset"].split("+"))
        assert [row[f"in_{d}"] for d in ders] == [int(d in members) for d in ders]
        assert all(pd.isna(row[f"w_{d}"]) == (d not in members) for d in ders)


def test_the_robustness_csv_is_tidy(tmp_path: Path) -> None:
    result = analyze_robustness(example("wt-chp"), small_table("wt-chp"))
    header, rows = result.csv_rows()
    with open(tmp_path / "robustness.csv", "w", newline="") as fh:
        csv.writer(fh).writerows([header, *rows])
    frame = pd.read_csv(tmp_path / "robustness.csv")
    numeric(frame, {"subset"})
    assert frame["in_SGen1"].tolist() == [int("SGen1" in s) for s in result.subsets]
