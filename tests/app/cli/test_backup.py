"""``python -m app.backup``: its progress, a Ctrl-C that leaves nothing behind, and a plain-text ``--help``.

The command runs as a user runs it, in its own process, on stores written by ``SqliteStorage``.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

from app.storage import INLINE_BYTES, BatchRecord, SqliteStorage
from app.storage.backup import DATABASE
from tests.conftest import ROOT


def _store(data_dir: Path, *, inline_mib: int = 0, files: int = 0) -> Path:
    """A store of one map: ``inline_mib`` MiB of batches in the database's pages, ``files`` batches as payload files."""
    storage = SqliteStorage(data_dir / DATABASE)
    try:
        storage.create_map("m", {"name": "m"}, "t0")
        inline = bytes(range(256)) * (INLINE_BYTES // 256)  # as big as a batch kept in its row gets
        for _ in range(inline_mib // 32):  # 32 MiB a transaction
            storage.append_batches([BatchRecord("m", None, inline, "t", 1)] * (32 * 2**20 // INLINE_BYTES))
        storage.append_batches([BatchRecord("m", None, bytes([k]) * (INLINE_BYTES + 1), "t", 1) for k in range(files)])
    finally:
        storage.close()
    return data_dir


def _backup(*args: str, **popen: object) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "app.backup", *args], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **popen)  # type: ignore[call-overload]


def test_progress_lines_give_each_stage_with_its_total_and_rate(tmp_path: Path) -> None:
    data = _store(tmp_path / "data", inline_mib=32, files=3)
    copy = tmp_path / "copy.sqlite3"
    process = _backup(str(copy), "--data-dir", str(data))
    out, err = process.communicate(timeout=120)
    assert process.returncode == 0, err
    assert out.startswith(f"{copy}: ") and "pages copied" in out
    lines = err.splitlines()
    said = re.fullmatch(rf"fuzzyrisk-backup: copying the database: ([\d,]+) pages of {data / DATABASE} to {copy}",
                        lines[0])
    assert said is not None, lines[0]
    pages = int(said[1].replace(",", ""))
    assert pages > 32 * 2**20 // 4096  # the 32 MiB of batches, in pages of 4 KiB
    assert re.fullmatch(rf"fuzzyrisk-backup: copying the database: {pages:,}/{pages:,} pages; [\d,.]+ pages/s, "
                        r"\d\d:\d\d elapsed, 00:00 left", lines[1]), lines[1]
    assert lines[2] == "fuzzyrisk-backup: putting payload files into the copy: 3 files"
    assert re.fullmatch(r"fuzzyrisk-backup: putting payload files into the copy: 3/3 files; [\d,.]+ files/s, "
                        r"\d\d:\d\d elapsed, 00:00 left", lines[3]), lines[3]
    assert len(lines) == 4


def test_ctrl_c_stops_the_copy_with_exit_130_one_line_and_nothing_at_the_destination(tmp_path: Path) -> None:
    data = _store(tmp_path / "data", inline_mib=256)  # half a second of copying or more, in steps of 4 MiB
    out_dir = tmp_path / "copies"
    out_dir.mkdir()
    copy = out_dir / "copy.sqlite3"
    process = _backup(str(copy), "--data-dir", str(data))
    try:
        assert process.stderr is not None
        started = process.stderr.readline()  # said as the copy of the pages begins
        assert started.startswith("fuzzyrisk-backup: copying the database: "), started + process.stderr.read()
        process.send_signal(signal.SIGINT)
        out, rest = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 130, rest
    assert out == ""
    assert rest.splitlines()[-1] == f"fuzzyrisk-backup: interrupted; nothing was written to {copy}"
    assert "Traceback" not in rest and "KeyboardInterrupt" not in rest
    assert list(out_dir.iterdir()) == []  # no copy, no .partial, no journal


def test_help_is_plain_text() -> None:
    result = subprocess.run([sys.executable, "-m", "app.backup", "--help"], check=False, cwd=ROOT, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert "DEST while the service runs" in result.stdout and "130 interrupted" in result.stdout
    for markup in ("``", "`", ":func:", ":mod:", "::"):
        assert markup not in result.stdout
