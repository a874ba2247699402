"""Box maxima (the dilation by the robot) against scipy.ndimage, which they replace in the service.

A maximum rounds nothing, so the arrays must be equal bit for bit: every dtype the service dilates
(float32 risk, uint8 masks), 2-D and 3-D, every half-width from 0 to past the array's size, the
edges (cells beyond the map count as ``cval``), several boxes accumulated into one result.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import ndimage

from planning import RiskField, _dilation_kernels
from planning.field import _boxes, _dilate_max, box_max, footprint
from planning.packed import PackedGrid

RES = 0.05


def _same_bits(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))


def _scipy_box(values: np.ndarray, halves: tuple[int, ...], cval: float) -> np.ndarray:
    return ndimage.maximum_filter(values, size=[2 * h + 1 for h in halves], mode="constant", cval=cval)


def _samples(rng: np.random.Generator, shape: tuple[int, ...], dtype: type) -> list[np.ndarray]:
    """Random values, values with many ties (risk is quantised), and masks."""
    if dtype is np.float32:
        return [rng.random(shape, dtype=np.float32),
                (np.round(rng.random(shape) * 8) / 8).astype(np.float32)]
    return [rng.integers(0, 256, shape, dtype=np.uint8), (rng.random(shape) < 0.2).astype(np.uint8)]


@pytest.mark.parametrize("dtype", [np.float32, np.uint8])
@pytest.mark.parametrize("shape", [(1, 1), (1, 17), (17, 1), (2, 3), (7, 5), (16, 16), (37, 53)])
def test_2d_box_max_is_scipys_maximum_filter_for_every_size(shape: tuple[int, int], dtype: type) -> None:
    rng = np.random.default_rng(sum(shape))
    for values in _samples(rng, shape, dtype):
        for halves in itertools.product(range(9), repeat=2):  # windows up to 17 cells, wider than some arrays
            for cval in (0.5, 0.0, 1.0) if dtype is np.float32 else (1, 0, 255):
                _same_bits(box_max(values, halves, cval), _scipy_box(values, halves, cval))


@pytest.mark.parametrize("dtype", [np.float32, np.uint8])
@pytest.mark.parametrize("shape", [(1, 1, 1), (1, 5, 1), (4, 1, 6), (5, 6, 7), (12, 9, 10)])
def test_3d_box_max_is_scipys_maximum_filter_for_every_size(shape: tuple[int, int, int], dtype: type) -> None:
    rng = np.random.default_rng(sum(shape))
    for values in _samples(rng, shape, dtype):
        for halves in itertools.product(range(5), repeat=3):
            cval = 0.5 if dtype is np.float32 else 1
            _same_bits(box_max(values, halves, cval), _scipy_box(values, halves, cval))


def test_large_grids_and_wide_windows() -> None:
    """Rows longer than a cache line's worth of vector, windows of up to 121 cells, edges on every side."""
    rng = np.random.default_rng(3)
    risk = rng.random((300, 1100), dtype=np.float32)
    unknown = (rng.random((300, 1100)) < 0.01).astype(np.uint8)
    for halves in [(1, 1), (4, 3), (0, 60), (60, 0), (17, 29), (149, 2), (200, 700)]:
        _same_bits(box_max(risk, halves, 0.5), _scipy_box(risk, halves, 0.5))
        _same_bits(box_max(unknown, halves, 1), _scipy_box(unknown, halves, 1))


def test_read_only_and_non_contiguous_inputs() -> None:
    rng = np.random.default_rng(4)
    base = rng.random((40, 60), dtype=np.float32)
    frozen = base.copy()
    frozen.setflags(write=False)
    for values in (frozen, base[::2, 1::3], base.T):
        _same_bits(box_max(values, (2, 3), 0.5), _scipy_box(values, (2, 3), 0.5))
    assert not frozen.flags.writeable  # left as it was


def test_kernel_in_place_and_accumulating() -> None:
    rng = np.random.default_rng(5)
    values = rng.random((3, 20, 30), dtype=np.float32)
    expected = ndimage.maximum_filter(values, size=(1, 7, 5), mode="constant", cval=0.5)
    work = values.copy()
    in_place = work.reshape(-1)
    _dilation_kernels.box_max_2d(_read_only(work), 3, 20, 30, 3, 2, np.float32(0.5), in_place, False)
    _same_bits(work, expected)
    acc = rng.random(values.shape, dtype=np.float32)
    want = np.maximum(acc, expected)
    _dilation_kernels.box_max_2d(_read_only(values), 3, 20, 30, 3, 2, np.float32(0.5), acc.reshape(-1), True)
    _same_bits(acc, want)


def _read_only(values: np.ndarray) -> np.ndarray:
    flat = values.reshape(-1)
    flat.flags.writeable = False  # as field._box_max passes it
    return flat


def _scipy_dilation(values: np.ndarray, fp: np.ndarray, outside: float) -> np.ndarray:
    """The dilation as the service computed it with scipy: a maximum filter per box of the footprint."""
    out = None
    for half in _boxes(fp):
        part = ndimage.maximum_filter(values, size=tuple(2 * h + 1 for h in half), mode="constant", cval=outside)
        out = part if out is None else np.maximum(out, part)
    return out


@pytest.mark.parametrize("ndim", [2, 3])
def test_dilation_by_the_robot_is_the_scipy_one(ndim: int) -> None:
    rng = np.random.default_rng(6)
    shape = (90, 70) if ndim == 2 else (30, 26, 14)
    risk = (np.round(rng.random(shape) ** 4 * 2**16) / 2**16).astype(np.float32)  # as maps quantise it
    observed = rng.random(shape) < 0.9
    radii = [0.0, 0.02, 0.05, 0.1, 0.17, 0.2, 0.3, 0.5, 1.0] if ndim == 2 else [0.0, 0.05, 0.1, 0.2, 0.3]
    for radius in radii:
        fp = footprint(radius, RES, ndim)
        field = RiskField(risk, RES, (0.0,) * ndim, observed=observed)
        _same_bits(field.dilated_risk(radius), _scipy_dilation(risk, fp, 0.5))
        expected = _scipy_dilation((~observed).view(np.uint8), fp, 1).astype(bool)
        _same_bits(field.dilated_unknown(radius), expected)
        # and the generic footprint dilation agrees (the boxes cover the footprint exactly)
        assert np.array_equal(_dilate_max(risk, fp, 0.5),
                              ndimage.grey_dilation(risk, footprint=fp, mode="constant", cval=0.5))


@pytest.mark.parametrize("ndim", [2, 3])
def test_eroded_validity_is_scipys_minimum_filter(ndim: int) -> None:
    rng = np.random.default_rng(7)
    shape = (50, 41) if ndim == 2 else (12, 11, 9)
    risk = rng.random(shape).astype(np.float32)
    field = RiskField(risk, RES, (0.0,) * ndim)
    grid = PackedGrid(field, 0.05, 0.8, True, 1.0)
    grid.endpoint_cells = (0, 17)
    expected = ndimage.minimum_filter(grid.valid, size=3, mode="constant", cval=False).reshape(-1)
    expected[[0, 17]] = grid.valid.reshape(-1)[[0, 17]]
    assert grid.eroded_valid_flat() == expected.tolist()


def test_negative_zero_gives_an_equal_maximum() -> None:
    """Maps' risk is never -0.0 (quantised from 16-bit codes); were it, only a zero's sign could differ."""
    rng = np.random.default_rng(8)
    values = np.where(rng.random((30, 30)) < 0.5, np.float32(-0.0), np.float32(0.0)).astype(np.float32)
    values[rng.random((30, 30)) < 0.05] = 0.25
    np.testing.assert_array_equal(box_max(values, (2, 1), 0.0), _scipy_box(values, (2, 1), 0.0))


def test_one_compiled_kernel_per_dtype() -> None:
    """Read-only and writable sources share a compilation (the first dilation of a process compiles)."""
    rng = np.random.default_rng(9)
    writable = rng.random((8, 9), dtype=np.float32)
    frozen = writable.copy()
    frozen.setflags(write=False)
    box_max(writable, (1, 1), 0.5)
    box_max(frozen, (1, 1), 0.5)
    box_max(rng.random((4, 5, 6), dtype=np.float32), (1, 1, 1), 0.5)
    float32 = [sig for sig in _dilation_kernels.box_max_2d.signatures if str(sig[0].dtype) == "float32"]
    assert len(float32) == 1 and not float32[0][0].mutable, _dilation_kernels.box_max_2d.signatures
