"""A command says once that it compiles, when numba compiles, and says nothing when every kernel is ready."""

from __future__ import annotations

import numba

from app.ops.compile_notice import on_first_compile


def test_the_first_compilation_is_said_once_and_a_compiled_kernel_is_not() -> None:
    @numba.njit(cache=False)
    def twice(x):  # type: ignore[no-untyped-def]
        return 2 * x

    said: list[str] = []
    with on_first_compile(lambda: said.append("compiling")):
        assert twice(2) == 4  # compiles for int
        assert twice(2.5) == 5.0  # compiles again, for float: still one line
    assert said == ["compiling"]
    with on_first_compile(lambda: said.append("again")):
        assert twice(3) == 6  # already compiled for int
    assert said == ["compiling"]
    assert twice(1j) == 2j  # outside the block: nobody is told
    assert said == ["compiling"]
