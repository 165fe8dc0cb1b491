"""A sweep's directory: what it is (``sweep.json``), every finished point as it comes
(``points.jsonl``, one JSON object a line, appended and flushed point by point, so an
interrupted or killed sweep keeps what it did), and the table (``table.parquet`` via pyarrow,
``table.csv``): one row per point, the varied keys, the metrics, ``error``.

A sweep resumed in the same directory reuses every point it finished without error (same scene
text, ``--set`` and ``--what``; the point named by its ``--set`` strings, so a wider ``--vary``
reuses the points the narrower one computed). A point that failed is computed again: its error
may have been its worker's, not its own.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from ..errors import RtctlError

META, POINTS, TABLE, CSV = "sweep.json", "points.jsonl", "table.parquet", "table.csv"

#: What must match for a directory's points to be reused.
IDENTITY = ("scene_sha256", "set", "what")


def identity(text: str, origin: str, sets, whats) -> dict:
    return {"scene": origin, "scene_sha256": hashlib.sha256(text.encode()).hexdigest(), "set": list(sets),
            "what": list(whats)}


class Store:
    """The directory of one sweep (see the module docstring).

    Parameters
    ----------
    out : str or Path
    ident : dict
        :func:`identity` of the sweep; a directory holding another sweep is refused.
    """

    def __init__(self, out, ident: dict):
        self.dir = Path(out)
        self.ident = ident
        meta = self.dir / META
        if meta.is_file():
            try:
                old = json.loads(meta.read_text())
            except (OSError, ValueError) as e:
                raise RtctlError(f"--out {self.dir}: unreadable {META} ({e}); remove it or pick another "
                                 "--out") from None
            differ = [k for k in IDENTITY if old.get(k) != ident[k]]
            if differ:
                raise RtctlError(f"--out {self.dir} holds a sweep with another {', '.join(differ)} "
                                 f"({old.get('scene')}, --what {','.join(old.get('what', []))}); pick another --out "
                                 "or remove that directory")
        self.previous = self._read()

    def _read(self) -> dict:
        """Finished points of earlier runs in this directory: ``--set`` strings -> record."""
        path, out = self.dir / POINTS, {}
        if not path.is_file():
            return out
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except ValueError:  # the line a killed sweep was writing
                continue
            key = tuple(rec.get("set", ()))
            if rec.get("error") is None:
                out[key] = rec
            else:
                out.pop(key, None)
        return out

    def open(self, meta: dict) -> None:
        """Start (or resume) writing: the directory and ``sweep.json``."""
        self.dir.mkdir(parents=True, exist_ok=True)
        self.write_meta(meta)
        self._points = open(self.dir / POINTS, "a", encoding="utf-8")

    def append(self, records) -> None:
        for rec in records:
            self._points.write(json.dumps(rec) + "\n")
        self._points.flush()

    def close(self) -> None:
        if getattr(self, "_points", None) is not None:
            self._points.close()
            self._points = None

    def write_meta(self, meta: dict) -> None:
        _replace(self.dir / META, json.dumps({**meta, **self.ident}, indent=1, default=str).encode())

    def write_table(self, rows: list[dict], meta: dict) -> tuple[Path, Path]:
        import pyarrow.csv
        import pyarrow.parquet

        table = to_arrow(rows).replace_schema_metadata({"rtctl.sweep": json.dumps({**meta, **self.ident},
                                                                                   default=str)})
        parquet, csv = self.dir / TABLE, self.dir / CSV
        pyarrow.parquet.write_table(table, str(parquet) + ".tmp")
        os.replace(str(parquet) + ".tmp", parquet)
        pyarrow.csv.write_csv(table, str(csv) + ".tmp")
        os.replace(str(csv) + ".tmp", csv)
        return parquet, csv


def _replace(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def rows(points, varies, records: dict) -> list[dict]:
    """One row per point, in product order: ``point``, the value of each ``--vary`` (column
    named by its key), the metrics (every column any point has, in the order they first
    appear; missing ones None), ``error``."""
    names: dict[str, None] = {}
    for p in points:
        names.update(dict.fromkeys(records[p.index]["metrics"]))
    out = []
    for p in points:
        rec = records[p.index]
        row = {"point": p.index}
        row.update({v.name: x for v, x in zip(varies, p.values)})
        row.update({k: rec["metrics"].get(k) for k in names})
        row["error"] = rec["error"]
        out.append(row)
    return out


def to_arrow(rows: list[dict]):
    """The rows as a pyarrow Table, one typed column each. A column of list or table values (a
    varied ``beam.segments``) holds them as the TOML literals ``--set`` takes, which CSV can hold
    too; a column mixing types holds strings."""
    import pyarrow as pa

    from .spec import toml_literal

    cols = {}
    for name in (rows[0] if rows else {}):
        values = [r[name] for r in rows]
        if any(isinstance(v, (list, tuple, dict)) for v in values):
            values = [None if v is None else toml_literal(v) for v in values]
        try:
            cols[name] = pa.array(values)
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, OverflowError):
            cols[name] = pa.array([None if v is None else json.dumps(v) if not isinstance(v, str) else v
                                   for v in values])
    return pa.table(cols)


def read_table(out) -> list[dict]:
    """The rows of ``out/table.parquet`` (floats as written, NaN kept)."""
    import pyarrow.parquet

    return pyarrow.parquet.read_table(Path(out) / TABLE).to_pylist()

