"""Read-ahead hints: ask the kernel to start reading a trajectory's HDF5 chunks before they are needed.

HDF5 reads a trajectory one chunk at a time, each read waiting on the disk. Telling the kernel which byte
ranges come next (``posix_fadvise(WILLNEED)``) lets it fetch them into the page cache in the background,
while the current batch is being read or trained on. Hints never change what is read; where the platform
or the HDF5 build cannot give chunk addresses, they are silently skipped, and so are datasets that are not
chunked (contiguous storage, as other tools may write it: there is no chunk index to look up).
"""

from __future__ import annotations

import os

import h5py
import numpy as np


class ChunkReadahead:
    """Byte ranges of row ranges of chunked 1-D-indexed datasets, and WILLNEED hints for them (none for
    contiguous datasets).

    f: the open HDF5 file; path: its path (opened once more, read-only, for the hints).
    """

    def __init__(self, f: h5py.File, path: str | os.PathLike):
        self._file = f
        self._path = os.fspath(path)
        self._fd: int | None = None
        self._tables: dict[str, tuple[int, np.ndarray, np.ndarray]] = {}
        self._unchunked: set[str] = set()
        self.enabled = hasattr(os, "posix_fadvise")

    def _table(self, name: str, hi: int) -> tuple[int, np.ndarray, np.ndarray] | None:
        """(rows per chunk, byte offset per chunk, byte size per chunk) covering rows [0, hi) at least;
        offset -1 for chunks not written. None for a dataset that is not chunked."""
        if name in self._unchunked:
            return None
        table = self._tables.get(name)
        if table is None or len(table[1]) * table[0] < hi:  # new, or built before a writer appended rows
            ds = self._file[name]
            if ds.chunks is None:  # contiguous: nothing to look up, so nothing to hint
                self._unchunked.add(name)
                return None
            if self._file.swmr_mode:  # a file a live writer is still appending to
                ds.refresh()
            rows = ds.chunks[0]
            n = -(-ds.shape[0] // rows)
            offsets = np.full(n, -1, dtype=np.int64)
            sizes = np.zeros(n, dtype=np.int64)

            def visit(info) -> None:
                k = info.chunk_offset[0] // rows
                if k < n:
                    offsets[k], sizes[k] = info.byte_offset, info.size

            ds.id.chunk_iter(visit)
            table = self._tables[name] = (rows, offsets, sizes)
        return table

    def byte_ranges(self, name: str, lo: int, hi: int) -> list[tuple[int, int]]:
        """(start, stop) file byte ranges holding rows [lo, hi) of dataset ``name``, adjacent chunks merged."""
        table = self._table(name, hi) if hi > lo else None
        if table is None:
            return []
        rows, offsets, sizes = table
        ks = np.arange(lo // rows, (hi - 1) // rows + 1)
        ks = ks[ks < len(offsets)]
        ks = ks[offsets[ks] >= 0]
        if len(ks) == 0:
            return []
        order = np.argsort(offsets[ks])
        starts, stops = offsets[ks][order], offsets[ks][order] + sizes[ks][order]
        ranges: list[tuple[int, int]] = []
        for start, stop in zip(starts.tolist(), stops.tolist(), strict=True):
            if ranges and start <= ranges[-1][1]:
                ranges[-1] = (ranges[-1][0], max(ranges[-1][1], stop))
            else:
                ranges.append((start, stop))
        return ranges

    def advise(self, names: tuple[str, ...] | list[str], lo: int, hi: int) -> None:
        """Hint that rows [lo, hi) of the datasets ``names`` will be read soon."""
        if not self.enabled:
            return
        try:
            if self._fd is None:
                self._fd = os.open(self._path, os.O_RDONLY)
            for name in names:
                for start, stop in self.byte_ranges(name, lo, hi):
                    os.posix_fadvise(self._fd, start, stop - start, os.POSIX_FADV_WILLNEED)
        except (OSError, NotImplementedError, RuntimeError):
            self.enabled = False  # an HDF5 build without chunk_iter, or a file system without fadvise

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
