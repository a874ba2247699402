"""The commands' progress: plain lines with the total, the rate and the time left where stderr is no terminal
(a log, a pipe), and a tqdm bar on a terminal."""

from __future__ import annotations

import io
import os
import pty
import re
import struct
import termios
from fcntl import ioctl

from app.cli.progress import Progress

PLAIN = re.compile(r"^prog: fusing: (?P<done>[\d,]+)/(?P<total>[\d,]+) scans(?P<note>, .*)?; (?P<rate>[\d.,]+) scans/s, "
                   r"\d\d:\d\d elapsed, (?P<left>\d\d:\d\d|\?) left$")


def test_a_plain_line_at_each_interval_and_at_the_end_with_total_rate_and_time_left() -> None:
    stream = io.StringIO()  # no terminal
    with Progress("prog", stream, every_s=0.0) as progress:  # every update is due
        progress.say("a log of 237 scans")
        progress.stage("fusing", 237, "scans")
        progress.update(32, "5,792 rays")
        progress.update(237, "42,897 rays")
    first, *lines = stream.getvalue().splitlines()
    assert first == "prog: a log of 237 scans"
    assert [PLAIN.match(line)["done"] for line in lines] == ["32", "237"]  # type: ignore[index]
    last = PLAIN.match(lines[-1])
    assert last is not None and last["total"] == "237" and last["note"] == ", 42,897 rays"
    assert float(last["rate"].replace(",", "")) > 0 and last["left"] == "00:00"


def test_lines_are_not_repeated_within_the_interval_but_the_last_figures_always_end_the_stage() -> None:
    stream = io.StringIO()
    with Progress("prog", stream, every_s=3600.0) as progress:
        progress.stage("fusing", 1000, "scans")
        for done in range(1, 1001):
            progress.update(done)
        progress.stage("writing", 3, "files")  # ends "fusing" with its last figures
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("prog: fusing: 1,000/1,000 scans; ")
    assert lines[1].startswith("prog: writing: 0/3 files; 0.0 files/s, ") and lines[1].endswith("? left")


def test_on_a_terminal_a_bar_shows_the_total_the_rate_and_the_note_with_lines_above_it() -> None:
    leader, follower = pty.openpty()
    ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))  # a terminal of 120 columns
    with os.fdopen(follower, "w", closefd=True) as terminal, Progress("prog", terminal) as progress:
        assert progress.terminal
        progress.stage("fusing", 237, "scans")
        progress.update(32, "5,792 rays")
        progress.say("a line of its own")
        progress.update(237, "42,897 rays")
    text = _read_all(leader).decode()
    assert "prog: a line of its own" in text
    screens = [s for s in re.split(r"[\r\n]+", text) if s.startswith("prog: fusing:")]
    assert "100%" in screens[-1] and "237/237" in screens[-1] and "scans/s" in screens[-1]
    assert "42,897 rays" in screens[-1] and "|" in screens[-1]  # the bar itself


def _read_all(fd: int) -> bytes:
    """Everything the terminal was sent, its writer having closed it (then Linux answers EIO); ``fd`` is closed."""
    shown = b""
    try:
        while chunk := os.read(fd, 65536):
            shown += chunk
    except OSError:  # EIO: everything was read
        pass
    finally:
        os.close(fd)
    return shown
