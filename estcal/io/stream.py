"""Rows of a CSV file or of standard input as they come: :class:`CsvStream` (``estcal online``).

The input is read line by line in bounded memory (a 10⁶-row file is never held whole), cut into
chunks, and each chunk is parsed by the dataset loader (:func:`estcal.io.dataset.dataset_from_table`,
or through a column map, :func:`estcal.io.dataset.dataset_from_mapped_table`) — the same checks and
messages as a whole file. The SHA-256 of the input consumed so far is kept
(:class:`estcal.io.integrity.PrefixHasher`), so that a checkpoint names exactly what it read and a
resumed run can refuse other input (:class:`estcal.io.integrity.CheckpointError`).
"""
from __future__ import annotations

import csv
import itertools
import re
import sys
import time
from dataclasses import dataclass

import numpy as np

from estcal.io.columnmap import as_column_map
from estcal.io.columns import DatasetError
from estcal.io.dataset import Dataset
from estcal.io.integrity import CheckpointError, PrefixHasher, file_sha256

__all__ = ["CsvStream", "Chunk", "read_dataset", "concat_datasets"]

_BINARY = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f]")  # never in CSV text (tab, LF, CR allowed)


def _lines(data: str, block: int = 1 << 20):
    """Lines of the input as they come, in bounded memory (a 10⁶-row file is never held whole).

    A file has been read and checked by the input layer already (folder, binary, encoding):
    here it is decoded block by block — UTF-8 with or without BOM, or UTF-16 with BOM — and
    split exactly as ``str.splitlines(keepends=True)`` splits the whole text (a block's last,
    possibly incomplete line, or a ``\\r`` whose ``\\n`` may start the next block, is carried
    over)."""
    if data == "-":
        yield from sys.stdin
        return
    import codecs

    with open(data, "rb") as fh:
        bom = fh.read(2)
    enc = "utf-16" if bom in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE) else "utf-8-sig"
    with open(data, encoding=enc, newline="") as fh:
        carry = ""
        while True:
            text = fh.read(block)
            if not text:
                break
            parts = (carry + text).splitlines(keepends=True)
            carry = parts.pop()
            yield from parts
        if carry:
            yield from carry.splitlines(keepends=True)


def _stdin_idle() -> bool:
    """True when standard input has no line ready now (a live stream between rows)."""
    import select

    try:
        return not select.select([sys.stdin], [], [], 0)[0]
    except (ValueError, OSError, TypeError, AttributeError):  # not a real file (tests): never idle
        return False


@dataclass
class Chunk:
    """Rows read from a stream: ``data`` (a Dataset, or None) and, when reading stopped at a bad
    row, ``error`` (the rows before it are in ``data``)."""

    data: Dataset | None
    error: Exception | None = None


class CsvStream:
    """The data rows of a CSV file or standard input (``"-"``), parsed in chunks through the
    dataset loader's checks (:func:`estcal.io.dataset.dataset_from_table`), with the SHA-256 of
    the input consumed so far for checkpoints.

    ``cut(n)`` says whether a chunk may end after data row n (counted from the start of the
    input, so a resumed run cuts where an uninterrupted one does); on standard input a chunk
    also ends when no row is waiting (a live stream is processed as it arrives). ``skip`` rows
    are hashed and not returned (a resumed run); ``expect`` = (bytes, sha256) of the
    checkpointed prefix, checked when they have been read. ``checked``: the file was checked
    whole (units, spread): chunks skip those checks. ``throttle``: seconds to wait after each
    row (a file replayed as a slow stream). :meth:`position` is the input up to the end of the
    last chunk returned."""

    def __init__(self, source: str, robot, *, cut=lambda n: n % 1024 == 0, measure=None, skip: int = 0,
                 expect=None, checked: bool = False, throttle: float = 0.0, column_map=None):
        self.source, self.robot, self.cut = source, robot, cut
        self.cmap = as_column_map(column_map)
        self._pending = []  # the first line of a file without a header row: a data row
        self.where = "<stdin>" if source == "-" else source
        self.allow_none = measure is not None
        self.skip, self.expect, self.checked, self.throttle = int(skip), expect, checked, float(throttle)
        self.hasher = PrefixHasher()
        self.input_sha256 = None if source == "-" else file_sha256(source)
        self.rows = 0  # data rows read (skipped ones included)
        self._it = self._numbered()
        self._at = None
        self._header()
        if self._at is None:
            self._at = self._mark()

    def position(self) -> dict:
        """Where the stream stood after the last chunk returned, as a checkpoint records it."""
        h, n, line = self._at
        return {"line": line, "input_bytes": n, "input_sha256_prefix": h.hexdigest(),
                "input_sha256": self.input_sha256}

    @property
    def last_line(self) -> int:
        return self._at[2]

    def _mark(self, line=None):
        return self.hasher.h.copy(), self.hasher.n, self.header_line if line is None else line

    def _numbered(self):
        src = enumerate(_lines(self.source), start=1)
        while True:
            try:
                ln, text = next(src)
            except StopIteration:
                return
            except UnicodeDecodeError:
                raise DatasetError(f"{self.where}: input is not UTF-8 text — send the CSV as UTF-8") from None
            bad = _BINARY.search(text)
            if bad:
                raise DatasetError(f"{self.where}, line {ln}, column {bad.start() + 1}: control character "
                                   f"0x{ord(bad.group()):02x} — binary data, not CSV text")
            self.hasher.update(text.encode("utf-8"))  # the consumed prefix, named in checkpoints
            yield ln, text

    def _header(self) -> None:
        from estcal.base.textinput import sniff_delimiter

        while True:
            before = self.hasher.h.copy(), self.hasher.n
            try:
                self.header_line, text = next(self._it)
            except StopIteration:
                raise DatasetError(f"{self.where}: empty input (expected a header row)") from None
            if text.strip():
                break
        first = text.lstrip("\ufeff")
        self.delimiter = sniff_delimiter(first)
        self.header = [h.strip() for h in next(csv.reader([first], delimiter=self.delimiter))]
        self._header_checked = False
        cols = self.cmap.columns if self.cmap is not None else None
        if cols is not None and self.header != cols:  # a file without a header row (the map's columns:)
            from estcal.io.columns import is_number

            if not all(is_number(h) for h in self.header if h):
                raise DatasetError(f"{self.where}, line {self.header_line}: the input has a header row "
                                   f"({', '.join(self.header[:6])}{'…' if len(self.header) > 6 else ''}) that "
                                   f"differs from columns: ({self.cmap.at('columns')}) — remove columns: from the "
                                   f"map or make it the input's header")
            self._pending = [(self.header_line, text)]
            self.header, self.header_line = list(cols), 0
            self._at = (before[0], before[1], 0)  # the first data line is not consumed yet

    def _check_header(self) -> None:
        """The loader's header checks, once (after the first data line was read and found to be text);
        through the column map, its checks of the header (columns it names, joints it leaves unmapped)."""
        self._header_checked = True
        ds = self._header_dataset()
        if ds.kind == "none" and not self.allow_none:
            raise DatasetError(f"{self.where}, line {self.header_line}: no measurement columns (x,y,z / x1..zk / "
                               f"x,y,z,qw,qx,qy,qz)")

    def layout(self) -> Dataset:
        """A dataset of no rows with the input's columns (joints, measurement kind, points), read from its
        header before any row: what a free set chosen by measurement needs (``estcal online`` on standard
        input). A header that does not read as a dataset raises the loader's :class:`DatasetError`."""
        return self._header_dataset()

    def _header_dataset(self) -> Dataset:
        from estcal.base.textinput import CsvTable
        from estcal.io.dataset import dataset_from_table

        header = self.header
        if self.cmap is not None:
            from estcal.io.columnmap import ColumnMapError, apply_column_map

            rb = self.robot
            try:
                header = apply_column_map(CsvTable(header, [], [], self.header_line, self.delimiter, self.where),
                                          self.cmap, rb.joint_names, rb.joint_types)[0].header
            except ColumnMapError as exc:
                raise DatasetError(str(exc)) from None
        empty = CsvTable(header, None, [], self.header_line, self.delimiter, self.where,
                         numeric=np.zeros((0, len(header))))
        return dataset_from_table(empty, self.robot, check_units=False)

    def _check_prefix(self) -> None:
        """The input read so far (up to :meth:`position`) is the checkpointed run's."""
        h, n, _ = self._at
        if self.expect is not None and (n, h.hexdigest()) != tuple(self.expect):
            raise CheckpointError(f"{self.where} differs from the checkpointed input (SHA-256 of the rows already "
                                  f"processed does not match)")

    def __iter__(self):
        if self.skip == 0:
            self._check_prefix()
        texts, lines, raw = [], [], []
        for ln, text in itertools.chain(self._pending, self._it):
            raw.append(text)
            if not text.strip():
                continue
            if not self._header_checked:
                self._check_header()
            self.rows += 1
            if self.rows <= self.skip:  # already in the checkpoint: hashed, not processed again
                raw = []
                if self.rows == self.skip:
                    self._at = self._mark(ln)
                    self._check_prefix()
                continue
            texts.append(text)
            lines.append(ln)
            if self.throttle:
                time.sleep(self.throttle)
            if self.cut(self.rows) or (self.source == "-" and _stdin_idle()):
                yield from self._chunks(texts, lines, raw)
                texts, lines, raw = [], [], []
        if texts:
            yield from self._chunks(texts, lines, raw)
        if not self._header_checked:
            self._check_header()
        if self.rows < self.skip:
            raise CheckpointError(f"{self.where} has {self.rows} data rows, fewer than the {self.skip} already "
                                  f"processed")

    def _parse(self, texts, lines):
        from estcal.base.textinput import CsvTable
        from estcal.io.dataset import dataset_from_mapped_table, dataset_from_table

        try:
            records = list(csv.reader(texts, delimiter=self.delimiter))
        except csv.Error as exc:
            raise DatasetError(f"{self.where}, line {lines[0]}: not a valid CSV line ({exc})") from None
        if len(records) != len(texts):
            raise DatasetError(f"{self.where}, line {lines[0]}: a quoted field spans lines — one row per line")
        table = CsvTable(self.header, records, lines, self.header_line, self.delimiter, self.where)
        if self.cmap is not None:
            ds = dataset_from_mapped_table(table, self.cmap, self.robot, check_units=not self.checked)
        else:
            ds = dataset_from_table(table, self.robot, check_units=not self.checked)
        if ds.kind == "none" and not self.allow_none:
            raise DatasetError(f"{self.where}: no measurement columns (x,y,z / x1..zk / x,y,z,qw,qx,qy,qz)")
        return ds

    def _chunks(self, texts, lines, raw):
        """The rows as one Dataset; at a bad row, the rows before it with the row's own error (the
        position then ends with the last good row), then the rows after it the same way."""
        start = self._at
        try:
            ds = self._parse(texts, lines)
            self._at = self._mark(lines[-1])
            yield Chunk(ds)
            return
        except (DatasetError, ValueError) as exc:
            bad, err = None, exc
            for i in range(len(texts)):  # the first row that fails alone (the error path only)
                try:
                    self._parse(texts[i:i + 1], lines[i:i + 1])
                except (DatasetError, ValueError) as row_exc:
                    bad, err = i, row_exc
                    break
        if bad is None:  # only the rows together fail (e.g. their spread): no row to blame
            yield Chunk(None, err)
            return
        h, nbytes, line = start[0].copy(), start[1], start[2]
        seen = 0
        for text in raw:  # the input up to the last good row
            if seen == bad:
                break
            b = text.encode("utf-8")
            h.update(b)
            nbytes += len(b)
            seen += bool(text.strip())
        self._at = (h, nbytes, lines[bad - 1] if bad else line)
        yield Chunk(self._parse(texts[:bad], lines[:bad]) if bad else None, err)
        if bad + 1 < len(texts):  # a caller that skips bad rows goes on with the next ones
            self._at = start
            at = [j for j, t in enumerate(raw) if t.strip()][bad]  # the bad row among the lines read
            yield from self._chunks(texts[bad + 1:], lines[bad + 1:], raw[at + 1:])


#: rows per chunk of :func:`read_dataset` (a chunk is parsed as text, then kept as floats), and the file
#: size above which it streams (below, the whole text costs little and the loader reads it at once)
READ_CHUNK_ROWS = 4096
STREAM_ABOVE_BYTES = 1 << 20


def _count_lines(path) -> int:
    """Newlines in a file (binary, 1 MiB at a time): an upper bound of its data rows + 1."""
    n = 0
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            n += block.count(b"\n")
    return n


def concat_datasets(parts: list) -> Dataset:
    """One dataset from consecutive parts of one file (as :func:`read_dataset` reads them)."""
    first = parts[0]
    if len(parts) == 1:
        return first

    def cat(get):
        a = [get(p) for p in parts]
        return None if a[0] is None else np.concatenate(a)

    ds = Dataset(list(first.joint_names), cat(lambda p: p.readings), first.kind, cat(lambda p: p.points),
                 cat(lambda p: p.R), cat(lambda p: p.p), {k: cat(lambda p, k=k: p.context[k]) for k in first.context},
                 {k: cat(lambda p, k=k: p.columns.get(k, np.full(p.n, np.nan))) for k in first.columns},
                 cat(lambda p: p.lines), first.path, list(dict.fromkeys(w for p in parts for w in p.warnings)))
    ds.source_header, ds.renamed, ds.coordinates = first.source_header, dict(first.renamed), first.coordinates
    return ds


def read_dataset(path, robot, *, column_map=None, max_rows: int | None = None, check_units: bool = True):
    """A dataset file read in bounded memory: ``(dataset, data rows in the file)``.

    Large files are streamed (:class:`CsvStream`, :data:`READ_CHUNK_ROWS` rows parsed as text at a time,
    kept as floats), so that the text of a file that is not a plain numeric table (a column map, quoted
    fields, blank lines …) is never held whole — ~5 kB of Python strings per row otherwise. ``max_rows``:
    keep an evenly spaced sample of about that many rows (every k-th row; lines stay the file's). Small
    files and plain numeric tables (:func:`estcal.io.dataset.load_dataset`'s fast path) are read as
    ``load_dataset`` reads them; the unit checks are those of the whole file (``check_units``)."""
    from pathlib import Path

    from estcal.io.dataset import _read_numeric, check_dataset_units, load_dataset

    from estcal.base.textinput import check_input_file

    p = check_input_file(Path(path), "dataset", DatasetError)  # a folder, a missing file: named first
    cmap = as_column_map(column_map)
    table = None if cmap is not None else _read_numeric(p)
    if table is not None or p.stat().st_size < STREAM_ABOVE_BYTES:
        if table is not None:
            from estcal.io.dataset import dataset_from_table

            ds = dataset_from_table(table, robot, check_units=check_units)
        else:
            ds = load_dataset(p, robot, check_units=check_units, column_map=cmap)
        total = ds.n
        if max_rows is not None and ds.n > max_rows:
            ds = ds.subset(np.arange(0, ds.n, -(-ds.n // max_rows)))
        return ds, total
    every = max(1, -(-_count_lines(p) // max_rows)) if max_rows else 1
    parts, seen = [], 0
    src = CsvStream(str(p), robot, cut=lambda n: n % READ_CHUNK_ROWS == 0, checked=True, column_map=cmap)
    for chunk in src:
        if chunk.error is not None:
            raise chunk.error
        ds = chunk.data
        if every > 1:
            ds = ds.subset(np.flatnonzero((seen + np.arange(ds.n)) % every == 0))
        seen += chunk.data.n
        if ds.n:
            parts.append(ds)
    if not parts:
        raise DatasetError(f"{p}: header only, no data rows")
    ds = concat_datasets(parts)
    if check_units:
        header = None if cmap is not None else src.header
        if cmap is not None:  # the mapped columns: one point x,y,z with an orientation, else x1…zk
            header = ["x", "y", "z"] if cmap.rpy or cmap.quaternion else [f"x{i + 1}" for i in range(len(cmap.points))]
        check_dataset_units(ds, robot, header, cmap)
    return ds, seen
