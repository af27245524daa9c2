"""A store in a scan log's folder: its chunks' bytes in append-only chunk files, the store as an
index of them.

A segment base is the whole map where the segment began, but consecutive bases share most of
it: the map's store shares every chunk it has not rewritten with each base taken from it, and a
chunk never changes in place (``store``). So a chunk object written once is named again by the
next base's index, never written again (``ChunkPlaces``): a base costs the chunks the map
rewrote since the last base (about the window's voxels) and its index, not the whole map.

A chunk's bytes are its four arrays back to back: offsets (uint16), counts (uint8), classes
(uint8), values (uint32), little endian. An index holds per chunk its key, the number of its
chunk file in the index's ``names``, the offset there, its voxels and its class entries.
"""

from __future__ import annotations

import weakref

import numpy as np

from convbki_core.memory.store import VoxelStore, _Chunk

INDEX_NAMES = ("keys", "chunk_file", "offset", "voxels", "entries", "names")


def chunks_of(store: VoxelStore) -> list[tuple[tuple[int, int, int], _Chunk]]:
    """The store's (key, chunk) pairs as they are now (chunks never change in place, so this may
    run on another thread while the store goes on)."""
    return list(store._chunks.items())


def chunk_buffers(chunk: _Chunk) -> list[np.ndarray]:
    return [chunk.offsets, chunk.counts, chunk.classes, chunk.values]


def chunk_size(chunk: _Chunk) -> int:
    return 3 * chunk.offsets.size + 5 * chunk.classes.size


class ChunkPlaces:
    """Where the chunk objects written so far are (file name, offset), for as long as they live."""

    def __init__(self):
        self._places: dict[int, tuple] = {}

    def get(self, chunk: _Chunk) -> tuple[str, int] | None:
        known = self._places.get(id(chunk))
        return None if known is None or known[0]() is not chunk else (known[1], known[2])

    def put(self, chunk: _Chunk, name: str, offset: int) -> None:
        key = id(chunk)
        self._places[key] = (weakref.ref(chunk, lambda _, key=key: self._places.pop(key, None)), name, offset)

    def forget(self, names: set[str]) -> None:
        """Chunk files deleted: their chunks must be written again."""
        for key, known in list(self._places.items()):
            if known[1] in names:
                self._places.pop(key, None)


def store_of_index(index: dict[str, np.ndarray], files: dict[str, np.ndarray], num_classes: int,
                   prior: float, places: ChunkPlaces | None = None) -> VoxelStore:
    """The store an index names, its chunk files' bytes in ``files`` (name -> uint8 array, e.g. a
    memory map); raises ValueError where they do not fit together. ``places``: note where each
    chunk read is, so that a base taken from this store later names them rather than writing them."""
    keys, numbers, offsets = index["keys"], index["chunk_file"], index["offset"]
    voxels, entries, names = index["voxels"], index["entries"], [str(name) for name in index["names"]]
    count = len(keys)
    if keys.shape != (count, 3) or any(len(a) != count for a in (numbers, offsets, voxels, entries)):
        raise ValueError("its index is damaged")
    if count and (numbers.min() < 0 or numbers.max() >= len(names) or (voxels < 0).any() or (entries < 0).any()
                  or (offsets < 0).any()):
        raise ValueError("its index names places that do not exist")
    if len(np.unique(keys, axis=0)) != count:
        raise ValueError("it holds a chunk twice")
    store = VoxelStore(num_classes, prior)
    arrays = [files[name] for name in names]
    for key, number, offset, n, m in zip(keys.tolist(), numbers.tolist(), offsets.tolist(), voxels.tolist(),
                                         entries.tolist()):
        data = arrays[number]
        end = offset + 3 * n + 5 * m
        if end > data.size:
            raise ValueError(f"chunk file {names[number]} is shorter than its index says")
        raw = data[offset:end]
        # Copies: a chunk's arrays own their memory (the store's rule), never views of a file.
        chunk = _Chunk(raw[:2 * n].view("<u2").astype(np.uint16), raw[2 * n:3 * n].astype(np.uint8),
                       raw[3 * n:3 * n + m].astype(np.uint8), raw[3 * n + m:end - offset].view("<u4").astype(np.uint32))
        if int(chunk.counts.sum(dtype=np.int64)) != m or (m and int(chunk.classes.max()) >= num_classes):
            raise ValueError(f"chunk file {names[number]} holds a chunk that does not fit its index")
        store._replace_chunk(tuple(key), None, chunk)
        if places is not None:
            places.put(chunk, names[number], offset)
    return store
