"""Reading the text files users give estcal: one place for the checks every input needs.

Every command reads its inputs (datasets, robot files, URDF, candidate poses,
state JSON) through :func:`read_text`, and CSV tables through :func:`read_csv`,
so that the same problems get the same clear message, naming the file and,
where it helps, the line and column:

* the path is a folder, is missing, or cannot be read;
* the file is binary (a NUL byte or other control characters), or is not
  UTF-8 text (the byte, line and column are named; a UTF-8 or UTF-16 byte-order
  mark is accepted and removed — spreadsheets write them);
* CSV: the delimiter is sniffed from the header line (``,`` then ``;`` then a
  tab), blank lines are skipped while keeping the physical line numbers (a record
  knows the line it starts on), and a header written by ``numpy.savetxt`` with its
  default ``# `` comment prefix is named as such.

The caller passes its own exception class (``DatasetError``, ``RobotFileError`` …)
so that callers keep catching one type per kind of file.
"""
from __future__ import annotations

import codecs
import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path

from .errors import InputError

__all__ = ["InputError", "check_input_file", "read_text", "read_csv", "read_csv_header", "read_json", "read_yaml", "parse_csv_text", "CsvTable",
           "DELIMITERS", "ascii_skeleton", "lookalike_note"]

# spreadsheet exports: comma, semicolon (locales with a decimal comma), tab
DELIMITERS = (",", ";", "\t")
_DELIM_NAME = {",": "','", ";": "';'", "\t": "tab"}
# control characters that never occur in a text file (tab, LF, CR, FF, VT excluded)
_CONTROL = {chr(c) for c in range(32)} - {"\t", "\n", "\r", "\x0b", "\x0c"}


def check_input_file(path, what: str = "input", error=InputError) -> Path:
    """``path`` as a Path if it is a readable regular file, else ``error`` with a clear message."""
    p = Path(path)
    if str(path) == "-":  # the rows of a batch command are read several times (header, units, data)
        raise error(f"-: only `estcal online` reads rows from standard input — save the {what} to a file "
                    f"and give its path")
    if p.is_dir():
        raise error(f"{p}: is a folder, not a {what} file — give the path of the file itself")
    if not p.exists():
        parent = p.parent
        hint = "" if str(parent) in ("", ".") or parent.is_dir() else f" (the folder {parent} does not exist)"
        raise error(f"{p}: {what} file not found{hint}")
    if not p.is_file():
        raise error(f"{p}: not a regular file (a device, socket or pipe?); give a {what} file")
    if not os.access(p, os.R_OK):
        raise error(f"{p}: permission denied — the {what} file is not readable by this user")
    return p


def _position(text: str, offset: int) -> tuple[int, int]:
    """1-based (line, column) of character ``offset`` in ``text``."""
    line = text.count("\n", 0, offset) + 1
    col = offset - (text.rfind("\n", 0, offset) + 1) + 1
    return line, col


def decode_text(data: bytes, where: str, what: str = "input", error=InputError) -> str:
    """Decode the bytes of a text file (UTF-8, with or without BOM, or UTF-16 with BOM)."""
    if data.startswith(codecs.BOM_UTF8):
        data = data[len(codecs.BOM_UTF8):]
    elif data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            return data.decode("utf-16")
        except UnicodeDecodeError as exc:
            raise error(f"{where}: starts with a UTF-16 byte-order mark but is not valid UTF-16 "
                        f"(byte {exc.start}) — save the {what} file as UTF-8") from None
    nul = data.find(b"\0")
    if nul >= 0:
        line = data.count(b"\n", 0, nul) + 1
        raise error(f"{where}: binary file (NUL byte at line {line}), not a {what} text file — "
                    f"export the {what} as a text file")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        head = data[:exc.start].decode("utf-8", errors="replace")
        line, col = _position(head + "?", len(head))
        raise error(f"{where}, line {line}, column {col}: byte 0x{data[exc.start]:02x} is not UTF-8 text — "
                    f"save the {what} file as UTF-8 (or it is not a text file)") from None
    for i, ch in enumerate(text):
        if ch in _CONTROL:
            line, col = _position(text, i)
            raise error(f"{where}, line {line}, column {col}: control character 0x{ord(ch):02x} — "
                        f"binary data, not a {what} text file")
    return text


def read_text(path, what: str = "input", error=InputError) -> str:
    """The content of the text file ``path`` (checked: a readable file, text, UTF-8/UTF-16)."""
    p = check_input_file(path, what, error)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise error(f"{p}: cannot read the {what} file ({exc.strerror or exc})") from None
    return decode_text(data, str(p), what, error)


@dataclass
class CsvTable:
    """A CSV file split into a header and records.

    ``lines[i]`` is the physical line on which record ``i`` starts (the header's
    line is ``header_line``), so messages name the line an editor shows."""

    header: list[str]
    rows: list[list[str]]
    lines: list[int]
    header_line: int
    delimiter: str
    where: str
    numeric: object = None  # (n, columns) float array when parsed by the numeric fast path (rows None)

    @property
    def delimiter_name(self) -> str:
        return _DELIM_NAME.get(self.delimiter, repr(self.delimiter))


def sniff_delimiter(header_line: str) -> str:
    """The delimiter of a header line: ``,`` if present, else ``;``, else a tab, else ``,``."""
    for d in DELIMITERS:
        if d in header_line:
            return d
    return ","


def parse_csv_text(text: str, where: str, what: str = "dataset", error=InputError,
                   delimiter: str | None = None) -> CsvTable:
    """Split CSV ``text`` into header and records, keeping physical line numbers."""
    lines = text.splitlines(keepends=True)
    first = next((ln for ln in lines if ln.strip()), "")
    delim = delimiter or sniff_delimiter(first)
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delim, strict=False)
    records, starts = [], []
    prev = 0
    try:
        for rec in reader:
            start = prev + 1
            prev = reader.line_num
            if not rec or (len(rec) == 1 and not rec[0].strip()):
                continue  # blank line (its number is still counted)
            records.append(rec)
            starts.append(start)
    except csv.Error as exc:
        raise error(f"{where}, line {prev + 1}: not a valid CSV line ({exc})") from None
    if not records:
        raise error(f"{where}: empty file (expected a header row and data rows)")
    header = [h.strip() for h in records[0]]
    if header and header[0].startswith("#"):
        raise error(f"{where}, line {starts[0]}: the header starts with '#' ({records[0][0].strip()!r}) — "
                    f"numpy.savetxt's comment prefix? remove the '# ' so the first column is named")
    return CsvTable(header, records[1:], starts[1:], starts[0], delim, where)


def read_csv(path, what: str = "dataset", error=InputError) -> CsvTable:
    """:func:`read_text` then :func:`parse_csv_text`."""
    p = Path(path)
    return parse_csv_text(read_text(p, what, error), str(p), what, error)


def read_csv_header(path, what: str = "dataset", error=InputError) -> list[str]:
    """The header row of a CSV file, read without loading the rest of the file.

    Same checks and messages as :func:`read_csv` on the lines up to the header (the rest of the
    file is checked when it is loaded): a caller that only needs the column names of a
    10⁶-row file then costs kilobytes, not the ~2.5 GB of Python strings a full parse takes."""
    p = check_input_file(path, what, error)
    try:
        with open(p, "rb") as fh:
            head = fh.readline()
            if head.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
                return read_csv(p, what, error).header  # line ends are two bytes: read it whole
            while head and not head.lstrip(codecs.BOM_UTF8).strip():
                line = fh.readline()  # blank lines before the header (their numbers still count)
                if not line:
                    break
                head += line
    except OSError as exc:
        raise error(f"{p}: cannot read the {what} file ({exc.strerror or exc})") from None
    return parse_csv_text(decode_text(head, str(p), what, error), str(p), what, error).header


def _syntax_json(exc):
    import json

    if isinstance(exc, json.JSONDecodeError):
        return exc.lineno, exc.colno, exc.msg
    return None


def _syntax_yaml(exc):
    import yaml

    if isinstance(exc, yaml.YAMLError):
        mark = getattr(exc, "problem_mark", None)
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
        return (mark.line + 1, mark.column + 1, problem) if mark is not None else (None, None, problem)
    return None


def _read_parsed(path, what, error, parse, syntax, kind):
    """``parse`` the text of ``path``; its syntax errors (``syntax(exc)`` → line, column,
    problem) become one-line ``error`` messages with the position."""
    p = Path(path)
    text = read_text(p, what, error)
    try:
        return parse(text)
    except RecursionError:
        raise error(f"{p}: invalid {kind} in the {what} file (nested too deeply)") from None
    except Exception as exc:  # noqa: BLE001 - only the parser's syntax errors are translated
        found = syntax(exc)
        if found is None:
            raise
        line, col, problem = found
        at = f", line {line}, column {col}" if line is not None else ""
        raise error(f"{p}{at}: invalid {kind} in the {what} file ({problem})") from None


def read_json(path, what: str = "JSON", error=InputError):
    """Parse the JSON file ``path``; a syntax error names its line and column."""
    import json

    return _read_parsed(path, what, error, json.loads, _syntax_json, "JSON")


def read_yaml(path, what: str = "YAML", error=InputError):
    """Parse the YAML file ``path`` (safe loader); a syntax error names its line and column."""
    import yaml

    return _read_parsed(path, what, error, yaml.safe_load, _syntax_yaml, "YAML")


# Letters of other scripts drawn like Latin ones (Unicode's confusables for the letters and digits of
# column names; NFKC folds the full-width and other compatibility forms): a header typed or pasted
# with one of them names another column, and a message that says "missing j1" beside a column
# that reads j1 leaves the user searching.
_LOOKALIKE = dict(zip(
    "аАВсСеЕНіІјЈКМоОрРѕЅТхХуУԁԛԝαΑΒΕΖΗιΙκΚΜνΝοΟρΡτΤυΥχΧ",
    "aABcCeEHiIjJKMoOpPsSTxXyYdqwaABEZHiIkKMvNoOpPtTuYxX"))


def ascii_skeleton(text: str) -> str:
    """``text`` with its look-alike letters replaced by the Latin letters they imitate (``ј1`` → ``j1``)."""
    import unicodedata

    return "".join(_LOOKALIKE.get(c, c) for c in unicodedata.normalize("NFKC", text))


def lookalike_note(text: str, meant: str) -> str | None:
    """When ``text`` differs from ``meant`` only by look-alike characters: the characters named, e.g.
    ``"its 'ј' is U+0458 CYRILLIC SMALL LETTER JE, not 'j' (U+006A)"``; else None."""
    import unicodedata

    if text == meant or ascii_skeleton(text) != meant:
        return None
    parts = []
    for c in dict.fromkeys(c for c in text if not c.isascii()):
        latin = ascii_skeleton(c)
        name = unicodedata.name(c, "unnamed character")
        parts.append(f"its {c!r} is U+{ord(c):04X} {name}, not {latin!r} (U+{ord(latin[0]):04X})")
    return "; ".join(parts)
