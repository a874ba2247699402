"""``python -m app.backup``: its progress, a Ctrl-C that leaves nothing behind, and a plain-text ``--help``.

The command runs as a user runs it, in its own process, on stores written by ``SqliteStorage``.
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from app.storage import INLINE_BYTES, BatchRecord, SqliteStorage
from app.storage.backup import DATABASE
from tests.conftest import ROOT

#: ``fcntl``'s F_SETPIPE_SZ (Linux; Python's ``fcntl`` names it from 3.10 on some builds only)
F_SETPIPE_SZ = getattr(fcntl, "F_SETPIPE_SZ", 1031)


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


def _full_pipe() -> tuple[int, int, bytes]:
    """A pipe (read end, write end) whose buffer is full: a process writing to it blocks until it is read."""
    read_end, write_end = os.pipe()
    fcntl.fcntl(write_end, F_SETPIPE_SZ, 4096)  # the smallest a pipe holds: one page
    os.set_blocking(write_end, False)
    junk = b""
    try:
        while True:
            junk += b"x" * os.write(write_end, b"x" * 512)
    except BlockingIOError:
        pass
    os.set_blocking(write_end, True)
    return read_end, write_end, junk


def test_ctrl_c_stops_the_copy_with_exit_130_one_line_and_nothing_at_the_destination(tmp_path: Path) -> None:
    # Interrupted in the middle of the copy, whatever the machine's load: its stderr is a full pipe, so the command
    # blocks at its first progress line, which it writes once the copy has begun; the Ctrl-C lands there. (Sent after
    # reading that line instead, it lost the race against the copy's end on a busy machine.)
    data = _store(tmp_path / "data", inline_mib=32)
    out_dir = tmp_path / "copies"
    out_dir.mkdir()
    copy = out_dir / "copy.sqlite3"
    read_end, write_end, junk = _full_pipe()
    # Ctrl-C as a terminal sends it: a suite run in the background (a shell's ``&``) hands its children SIGINT ignored,
    # and Python keeps an ignored SIGINT ignored
    process = subprocess.Popen([sys.executable, "-m", "app.backup", str(copy), "--data-dir", str(data)], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=write_end,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    os.close(write_end)
    try:
        deadline = time.monotonic() + 240.0  # a net against a hang: the wait ends on its condition
        wchan = Path(f"/proc/{process.pid}/wchan")
        while "pipe" not in wchan.read_text() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert process.poll() is None, "the command ended before it wrote its first progress line"
        assert (out_dir / "copy.sqlite3.partial").exists()  # blocked in the middle of the copy
        process.send_signal(signal.SIGINT)
        with os.fdopen(read_end, "rb") as err_pipe:
            err = err_pipe.read()  # to the end: the command's last lines, then its exit closes the pipe
        out, _ = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert err.startswith(junk)
    rest = err[len(junk):].decode()
    assert process.returncode == 130, rest
    assert out == b""
    # the last line (the progress line the Ctrl-C cut may precede it without its newline: its text waited in
    # stderr's buffer, and went out with this one)
    assert rest.endswith(f"fuzzyrisk-backup: interrupted; nothing was written to {copy}\n"), rest
    assert "Traceback" not in rest and "KeyboardInterrupt" not in rest
    assert list(out_dir.iterdir()) == []  # no copy, no .partial, no journal


def test_help_is_plain_text() -> None:
    result = subprocess.run([sys.executable, "-m", "app.backup", "--help"], check=False, cwd=ROOT, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert "DEST while the service runs" in result.stdout and "130 interrupted" in result.stdout
    for markup in ("``", "`", ":func:", ":mod:", "::"):
        assert markup not in result.stdout
