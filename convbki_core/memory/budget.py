"""The map's memory budget: where the global store stops growing, and the ceiling it never passes.

A ``VoxelStore`` with a budget (``StoreBudget``, bytes as ``VoxelStore.resident_bytes`` counts
them) maps as an unbounded one until its bytes reach the budget; from then on the map is *full*
and stops growing:

* the bytes that count are the store's resident bytes plus the bytes it *lent* the window
  (``take_window`` hands the window the voxels entering it and removes them from the store; the
  chunks they came from are the map's all the same, so a revisit neither frees room for new
  ground nor ends the full state);
* while full, a write goes only into a chunk the store holds or one it lent (its voxels come
  back from the window: old ground keeps its map, with what the window added to it); the voxels
  of every other chunk are dropped, forgotten as if never observed, and counted;
* past the *ceiling*, on the store's own resident bytes, nothing more is written at all (counted
  the same way), so memory stays bounded whatever the input does to the chunks already held.

Lent bytes are released as a lent chunk's voxels come back (as much as the chunk grows, up to
what it lent); what never comes back (voxels forgotten in the window) stays counted until the
chunk is written again, forgotten by ``forget_box`` or the store is cleared: the budget errs
towards full, never past the ceiling. A budget of 0 is no bound (the store as it always was).
"""

from __future__ import annotations

from dataclasses import dataclass

ChunkKey = tuple[int, int, int]


@dataclass(frozen=True)
class MemoryState:
    """What the map's memory budget says now (bytes as ``VoxelStore.resident_bytes`` counts them).

    ``store_bytes``: the store's resident bytes; ``lent_bytes``: bytes of the map the store lent
    the window (counted against the budget); ``budget_bytes`` / ``ceiling_bytes``: the budget and
    the hard ceiling (0: no bound); ``full``: the map stopped growing (store + lent >= budget);
    ``voxels_dropped``: voxels that left the window and were forgotten because the map was full
    or at its ceiling, since the store was made or cleared; ``times_full``: how often the map
    became full (the state is re-entered when a forgotten box made room and the map filled again).
    """

    store_bytes: int
    lent_bytes: int
    budget_bytes: int
    ceiling_bytes: int
    full: bool
    voxels_dropped: int
    times_full: int

    @property
    def bounded(self) -> bool:
        return self.budget_bytes > 0


class StoreBudget:
    """A store's budget and its bookkeeping: the chunks lent to the window (bytes by chunk key),
    the voxels dropped and how often the map became full. ``budget_bytes`` 0: no bound;
    ``ceiling_bytes``: the hard ceiling (>= the budget)."""

    __slots__ = ("budget_bytes", "ceiling_bytes", "full", "lent", "lent_bytes", "times_full", "voxels_dropped")

    def __init__(self, budget_bytes: int = 0, ceiling_bytes: int | None = None):
        self.lent: dict[ChunkKey, int] = {}
        self.lent_bytes = 0
        self.voxels_dropped = 0
        self.times_full = 0
        self.full = False
        self.budget_bytes = self.ceiling_bytes = 0
        self.set(budget_bytes, ceiling_bytes)

    def set(self, budget_bytes: int, ceiling_bytes: int | None = None) -> None:
        """A new budget (bytes; 0: none) and ceiling (bytes; None: the budget itself)."""
        budget_bytes = int(budget_bytes)
        ceiling_bytes = budget_bytes if ceiling_bytes is None else int(ceiling_bytes)
        if budget_bytes < 0 or (budget_bytes and ceiling_bytes < budget_bytes):
            raise ValueError(f"a store budget needs 0 <= budget <= ceiling, got {budget_bytes} and {ceiling_bytes}")
        self.budget_bytes, self.ceiling_bytes = budget_bytes, ceiling_bytes if budget_bytes else 0

    def copy(self) -> StoreBudget:
        """The same budget and counts, nothing lent (a copy of a store lends nothing: the window
        its chunks went to is the original's)."""
        other = StoreBudget(self.budget_bytes, self.ceiling_bytes)
        other.voxels_dropped, other.times_full, other.full = self.voxels_dropped, self.times_full, self.full
        return other

    def clear(self) -> None:
        """Nothing lent, nothing dropped, not full (the store was emptied)."""
        self.lent.clear()
        self.lent_bytes = self.voxels_dropped = self.times_full = 0
        self.full = False

    # -- admission ---------------------------------------------------------------------------
    def admits(self, key: ChunkKey, held: bool, resident_bytes: int) -> bool:
        """Whether voxels of chunk ``key`` may be written (``held``: the store has the chunk) with
        the store at ``resident_bytes``; the full state is brought up to date on the way."""
        if resident_bytes >= self.ceiling_bytes:
            self.note(resident_bytes)
            return False
        if not self.note(resident_bytes):
            return True
        return held or key in self.lent

    def note(self, resident_bytes: int) -> bool:
        """Bring the full state up to date with the store at ``resident_bytes``; returns it."""
        full = bool(self.budget_bytes) and resident_bytes + self.lent_bytes >= self.budget_bytes
        if full and not self.full:
            self.times_full += 1
        self.full = full
        return full

    # -- lending -----------------------------------------------------------------------------
    def lend(self, key: ChunkKey, nbytes: int) -> None:
        """The window took ``nbytes`` of chunk ``key`` (``take_window``)."""
        self.lent[key] = self.lent.get(key, 0) + nbytes
        self.lent_bytes += nbytes

    def returned(self, key: ChunkKey, grown: int) -> None:
        """Chunk ``key`` grew by ``grown`` bytes in a write: its lent bytes are released by as much."""
        lent = self.lent.get(key)
        if lent is None or grown <= 0:
            return
        released = min(lent, grown)
        self.lent_bytes -= released
        if released == lent:
            del self.lent[key]
        else:
            self.lent[key] = lent - released

    def release_inside(self, first: list[int], last: list[int]) -> None:
        """Forget what was lent of the chunks whose keys lie in [first, last] on every axis
        (``forget_box`` covered them whole: what the window held of them is forgotten too)."""
        for key in [key for key in self.lent if all(first[a] <= key[a] <= last[a] for a in range(3))]:
            self.lent_bytes -= self.lent.pop(key)
