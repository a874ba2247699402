"""The clients of ``bench/bench_abuse.py``: raw sockets for the attackers, a process for the innocent client.

* :class:`RawConn` and :func:`drive`: many HTTP/1.1 requests on non-blocking sockets, each
  sending its bytes on its own schedule (a header trickled a byte a second, a body of 60 MB in
  1 MiB pieces, then silence), all driven by one ``poll`` loop in one thread. Each records the
  answer's status and error message, how many bytes it had sent when the answer (or the close)
  came, and when. httpx cannot do this: it sends the whole body before it reads an answer, and
  a server that answers early (401 before the body) looks to it like a broken pipe.
* :class:`Innocent`: a client minding its own small map from a separate process (the
  attackers' threads and GIL must not be what is measured): one thread posts a binary 1080-beam
  scan, one reads ``risk.npy``, one asks for a plan now and then (``kinds``: the ones it runs), each on its own keep-alive
  connection, each request retried after ``Retry-After`` on a 503 as a well-behaved client
  does (the latency is the time until it is served). Samples are (start, end, kind, status,
  retries); it counts the scans acknowledged, so that the map's version can be checked.
"""

from __future__ import annotations

import http.client
import json
import multiprocessing
import select
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlencode

# ---------------------------------------------------------------- raw connections

Steps = Iterator[tuple[float, bytes]]  # (seconds to wait after the previous step was sent, bytes to send)


def request_head(method: str, target: str, headers: dict[str, str]) -> bytes:
    lines = [f"{method} {target} HTTP/1.1", "Host: 127.0.0.1", *(f"{k}: {v}" for k, v in headers.items())]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")


def body_steps(head: bytes, body: bytes | memoryview, *, chunk: int, interval_s: float) -> Steps:
    """The head at once, then ``body`` in pieces of ``chunk`` bytes, ``interval_s`` apart."""
    yield 0.0, head
    view = memoryview(body)
    for i in range(0, len(view), chunk):
        yield (interval_s if i else 0.0), bytes(view[i:i + chunk])


@dataclass
class RawConn:
    """One request on a non-blocking socket, sent step by step (see :func:`drive`)."""

    port: int
    steps: Steps
    label: str = ""

    def __post_init__(self) -> None:
        self.sock = socket.create_connection(("127.0.0.1", self.port), timeout=10)
        self.sock.setblocking(False)
        self.opened = time.monotonic()
        self.due = self.opened
        self.pending = b""
        self.sent = 0
        self.inbuf = bytearray()
        self.status: int | None = None
        self.message = ""
        self.ended: float | None = None  # when the answer was complete or the server closed
        self.how = ""  # "answered", "closed" (EOF without an answer), "reset", "deadline"
        self.sent_at_answer: int | None = None
        self.steps_done = False
        self._next: bytes | None = None

    @property
    def done(self) -> bool:
        return self.ended is not None

    @property
    def seconds(self) -> float:
        return (self.ended or time.monotonic()) - self.opened

    def advance(self, now: float) -> None:
        """Move the next step's bytes to ``pending`` once due (its delay runs from when the previous step was sent)."""
        if self.pending or self.steps_done:
            return
        if self._next is None:
            try:
                delay, data = next(self.steps)
            except StopIteration:
                self.steps_done = True
                return
            self._next, self.due = data, now + delay
        if now >= self.due:
            self.pending, self._next = self._next, None

    def on_writable(self) -> None:
        try:
            n = self.sock.send(self.pending)
        except BlockingIOError:
            return
        except (BrokenPipeError, ConnectionResetError):
            self._read_rest()
            if not self.done:
                self._end("reset")
            return
        self.sent += n
        self.pending = self.pending[n:]

    def on_readable(self) -> None:
        try:
            data = self.sock.recv(1 << 16)
        except BlockingIOError:
            return
        except ConnectionResetError:
            self._end("reset")
            return
        if not data:
            self._end("closed")
            return
        self.inbuf += data
        self._parse()

    def _read_rest(self) -> None:
        try:
            while not self.done:
                data = self.sock.recv(1 << 16)
                if not data:
                    break
                self.inbuf += data
                self._parse()
        except OSError:
            pass

    def _parse(self) -> None:
        head, sep, body = bytes(self.inbuf).partition(b"\r\n\r\n")
        if not sep:
            return
        lines = head.decode("latin-1").split("\r\n")
        length = 0
        for line in lines[1:]:
            key, _, value = line.partition(":")
            if key.strip().lower() == "content-length":
                length = int(value.strip())
        if len(body) < length:
            return
        self.status = int(lines[0].split()[1])
        try:
            self.message = str(json.loads(body[:length]).get("message", ""))
        except (ValueError, AttributeError):
            self.message = body[:200].decode("latin-1")
        self.sent_at_answer = self.sent
        self._end("answered")

    def _end(self, how: str) -> None:
        if self.ended is None:
            self.ended = time.monotonic()
            self.how = how if self.status is None else "answered"
        try:
            self.sock.close()
        except OSError:
            pass

    def close(self) -> None:
        """End this connection from the client's side (the bench is done with it)."""
        self._end("deadline")


def drive(conns: list[RawConn], deadline_s: float, *, stop: threading.Event | None = None) -> None:
    """Run every connection's steps until each is answered or closed, or ``deadline_s`` passes."""
    poller = select.poll()
    by_fd: dict[int, RawConn] = {}
    registered: set[int] = set()
    for c in conns:
        by_fd[c.sock.fileno()] = c
    end = time.monotonic() + deadline_s
    while True:
        now = time.monotonic()
        live = [c for c in conns if not c.done]
        if not live or now >= end or (stop is not None and stop.is_set()):
            break
        next_due = end
        for c in live:
            c.advance(now)
            if not c.pending and not c.steps_done:
                next_due = min(next_due, c.due)
        for fd, c in by_fd.items():
            if c.done:
                if fd in registered:
                    poller.unregister(fd)
                    registered.discard(fd)
                continue
            mask = select.POLLIN | (select.POLLOUT if c.pending else 0)
            if fd in registered:
                poller.modify(fd, mask)
            else:
                poller.register(fd, mask)
                registered.add(fd)
        timeout_ms = max(0, min(100, int((next_due - now) * 1000) + 1))
        for fd, event in poller.poll(timeout_ms):
            c = by_fd[fd]
            if c.done:
                continue
            if event & (select.POLLIN | select.POLLHUP | select.POLLERR):
                c.on_readable()
            if not c.done and event & select.POLLOUT and c.pending:
                c.on_writable()
    for c in conns:
        if not c.done:
            c.close()


# ---------------------------------------------------------------- the innocent client


@dataclass(frozen=True)
class InnocentSetup:
    port: int
    api_key: str
    name: str
    scans: list[tuple[bytes, dict[str, float]]]  # binary bodies and their queries
    plan: dict[str, Any]
    scan_every_s: float = 0.1
    read_every_s: float = 0.1
    plan_every_s: float = 1.0
    kinds: tuple[str, ...] = ("scan", "read", "plan")  # what it does, each in a thread of its own


class _Lean:
    """One keep-alive connection; reconnects after any error."""

    def __init__(self, port: int, key: str) -> None:
        self.port = port
        self.headers = {"Authorization": f"Bearer {key}"}
        self.conn: http.client.HTTPConnection | None = None

    def request(self, method: str, target: str, body: bytes | None = None,
                headers: dict[str, str] | None = None) -> tuple[int, bytes, dict[str, str]]:
        if self.conn is None:
            self.conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=300)
        try:
            self.conn.request(method, target, body=body, headers={**self.headers, **(headers or {})})
            response = self.conn.getresponse()
            data = response.read()
            return response.status, data, {k.lower(): v for k, v in response.getheaders()}
        except (OSError, http.client.HTTPException):
            self.close()
            raise

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None


def _loop(setup: InnocentSetup, kind: str, run: Any, stop: Any, busy: Any, out: list, acked: list) -> None:
    client = _Lean(setup.port, setup.api_key)
    every = {"scan": setup.scan_every_s, "read": setup.read_every_s, "plan": setup.plan_every_s}[kind]
    i = 0
    while not stop.is_set():
        if not run.is_set():
            client.close()  # a restart is coming: no kept-alive connection survives it
            run.wait(0.2)
            continue
        with busy.get_lock():
            busy.value += 1
        try:
            started = time.time()
            retries, status, note = 0, -1, ""
            while True:
                try:
                    if kind == "scan":
                        body, query = setup.scans[i % len(setup.scans)]
                        status, data, headers = client.request(
                            "POST", f"/maps/{setup.name}/scans?{urlencode(query)}", body,
                            {"Content-Type": "application/octet-stream"})
                    elif kind == "read":
                        status, data, headers = client.request("GET", f"/maps/{setup.name}/risk.npy")
                    else:
                        status, data, headers = client.request(
                            "POST", f"/maps/{setup.name}/plan", json.dumps(setup.plan).encode(),
                            {"Content-Type": "application/json"})
                except (OSError, http.client.HTTPException) as exc:
                    status, note = -1, f"{type(exc).__name__}"
                    break
                if status == 503 and time.time() - started < 120 and not stop.is_set():
                    retries += 1
                    time.sleep(float(headers.get("retry-after", "1")))
                    continue
                break
            if kind == "scan" and status == 200:
                acked.append(int(json.loads(data)["version"]))
            elif status != 200 and not note:
                try:
                    note = str(json.loads(data).get("message", ""))[:160]
                except ValueError:
                    note = data[:160].decode("latin-1")
            out.append((started, time.time(), kind, status, retries, note))
        finally:
            with busy.get_lock():
                busy.value -= 1
        i += 1
        stop.wait(every)
    client.close()


def _innocent_main(setup: InnocentSetup, run: Any, stop: Any, busy: Any, conn: Any) -> None:
    samples: list = []
    acked: list[int] = []
    threads = [threading.Thread(target=_loop, args=(setup, kind, run, stop, busy, samples, acked), daemon=True)
               for kind in setup.kinds]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    conn.send((samples, acked))
    conn.close()


class Innocent:
    """The innocent client in its own process; :meth:`pause` before a restart, :meth:`stop` for the samples."""

    def __init__(self, setup: InnocentSetup) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._run, self._stop = ctx.Event(), ctx.Event()
        self._busy = ctx.Value("i", 0)
        self._run.set()
        self._recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_innocent_main, args=(setup, self._run, self._stop, self._busy, send),
                                 daemon=True)
        self._proc.start()

    def pause(self, timeout_s: float = 180.0) -> bool:
        """Let the requests in flight finish and start no new ones; True once none is in flight."""
        self._run.clear()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._busy.value == 0:
                time.sleep(0.3)  # a loop between its check of run and its count
                if self._busy.value == 0:
                    return True
            time.sleep(0.05)
        return False

    def resume(self) -> None:
        self._run.set()

    def stop(self) -> tuple[list[tuple[float, float, str, int, int, str]], list[int]]:
        self._stop.set()
        self._run.set()
        samples, acked = self._recv.recv()
        self._proc.join(timeout=30)
        return samples, acked

    def kill(self) -> None:
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=10)
