"""Tests of models/tiff_pages.py: the strict TIFF reader of frames and videos."""

from __future__ import annotations

import io
import logging
import threading

import numpy as np
import pytest
import tifffile
from PIL import Image

from models.errors import UnsupportedFormatError
from models.tiff_pages import TiffDamaged, open_tiff, page_codes, page_shape


def tiff(array: np.ndarray, **options: object) -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, array, metadata=None, **options)
    return buffer.getvalue()


def test_a_truncated_multi_page_tiff_is_damaged_not_short(
    capsys: pytest.CaptureFixture[str],
) -> None:
    data = tiff(np.zeros((12, 16, 16), np.uint8))
    with pytest.raises(TiffDamaged, match="invalid page offset"):
        with open_tiff(data[: len(data) // 2]):
            pass
    assert capsys.readouterr().err == ""  # tifffile's warning no longer leaks to stderr


def damage_in_a_thread(data: bytes) -> list[BaseException]:
    """What reading ``data`` with :func:`open_tiff` raised in another thread."""
    raised: list[BaseException] = []

    def read() -> None:
        try:
            with open_tiff(data):
                pass
        except TiffDamaged as exc:
            raised.append(exc)

    thread = threading.Thread(target=read)
    thread.start()
    thread.join()
    return raised


def test_damage_is_found_whatever_the_global_log_level(caplog: pytest.LogCaptureFixture) -> None:
    """A root level of CRITICAL kept tifffile from logging its warning: half a video
    was read as a short one. Its logger's own level and propagation come back once
    the last of overlapping reads ends."""
    caplog.set_level(logging.CRITICAL)
    logger = tifffile.logger()
    data = tiff(np.zeros((12, 16, 16), np.uint8))
    with pytest.raises(TiffDamaged, match="invalid page offset"):
        with open_tiff(data[: len(data) // 2]):
            pass
    with open_tiff(data) as (_, pages):
        assert (logger.level, logger.propagate) == (logging.WARNING, False)
        assert len(damage_in_a_thread(data[: len(data) // 2])) == 1
        assert (logger.level, logger.propagate) == (logging.WARNING, False)
    assert pages == 12
    assert (logger.level, logger.propagate) == (logging.NOTSET, True)
    assert caplog.records == []


def test_separate_planes_come_back_samples_last() -> None:
    rgb = np.arange(3 * 4 * 5, dtype=np.uint8).reshape(3, 4, 5)
    with open_tiff(tiff(rgb, photometric="rgb", planarconfig="separate")) as (tif, pages):
        assert pages == 1
        page = tif.pages.first
        assert page_shape(page) == (4, 5, 3)
        np.testing.assert_array_equal(page_codes(page), np.moveaxis(rgb, 0, -1))


def test_an_undecodable_compression_is_named() -> None:
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(buffer, "TIFF", compression="tiff_lzw")
    with open_tiff(buffer.getvalue()) as (tif, _):
        with pytest.raises(UnsupportedFormatError, match="compression LZW.*deflate"):
            page_codes(tif.pages.first)


@pytest.mark.parametrize(("most", "counted"), [(None, 12), (20, 12), (12, 12), (5, 6), (0, 1)])
def test_pages_are_counted_up_to_one_past_the_limit(most: int | None, counted: int) -> None:
    """Past ``max_pages`` the count stops at one more: the caller refuses the file
    without indexing the rest."""
    buffer = io.BytesIO()
    with tifffile.TiffWriter(buffer) as writer:
        for _ in range(12):
            writer.write(np.zeros((4, 4), np.uint8))
    with open_tiff(buffer.getvalue(), max_pages=most) as (_, pages):
        assert pages == counted
