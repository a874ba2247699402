import numpy as np
import pytest

from fuzzyocc.reserved import Reserved


def test_a_longer_view_keeps_what_the_shorter_one_held_without_a_copy() -> None:
    slabs = Reserved(np.uint16, (4, 3), rows=1000)
    short = slabs.view(10)
    short[:] = np.arange(120, dtype=np.uint16).reshape(10, 4, 3)
    longer = slabs.view(500)
    assert np.shares_memory(short, longer)
    assert np.array_equal(longer[:10], short)
    longer[499] = 7  # every row reserved is writable
    assert slabs.view(500)[499, 0, 0] == 7
    with pytest.raises(ValueError, match="1000 are reserved"):
        slabs.view(1001)


def test_released_rows_are_given_back_and_read_as_zeros_the_rows_before_kept() -> None:
    slabs = Reserved(np.uint8, (4096,), rows=64)  # a row a page
    full = slabs.view(64)
    full[:] = 9
    slabs.release_from(16)
    assert np.all(slabs.view(64)[16:] == 0)
    assert np.all(slabs.view(16) == 9)
