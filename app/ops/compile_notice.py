"""Say when numba starts compiling: a cold kernel cache costs seconds that a command should explain.

numba compiles a kernel at its first call for a set of argument types, unless its cache
(``NUMBA_CACHE_DIR``, else beside the code) already holds the machine code; only a compilation,
never a load from the cache, is announced as a ``numba:compile`` event (numba's event API). A
command listens for the first one, so that a first run says why it is slow and later runs say
nothing.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from numba.core import event


class _First(event.Listener):
    """Calls ``say`` as the first compilation starts, and never again."""

    def __init__(self, say: Callable[[], None]) -> None:
        self.say: Callable[[], None] | None = say

    def on_start(self, ev: event.Event) -> None:
        if self.say is not None:
            say, self.say = self.say, None
            say()

    def on_end(self, ev: event.Event) -> None:
        pass


@contextlib.contextmanager
def on_first_compile(say: Callable[[], None]) -> Iterator[None]:
    """Within the block, call ``say()`` once, as numba starts to compile a kernel (never, when all are cached)."""
    with event.install_listener("numba:compile", _First(say)):
        yield
