"""What a run-time monitor remembers of each environment of a vectorized rollout: one entry per chunk so far."""

from collections.abc import Sequence
from typing import Any


class EnvironmentHistories:
    """One history per environment, grown by one entry per chunk; the environments step together.

    The first `append` sets how many environments there are; `reset` forgets them (call it when the
    environments reset).
    """

    def __init__(self):
        self._histories: list[list[Any]] = []

    def __len__(self) -> int:
        """How many environments there are (0 before the first chunk)."""
        return len(self._histories)

    def __getitem__(self, env: int) -> list[Any]:
        return self._histories[env]

    def __iter__(self):
        return iter(self._histories)

    @property
    def n_chunks(self) -> int:
        """How many chunks each environment has had: the index of the next one."""
        return len(self._histories[0]) if self._histories else 0

    def check(self, n_entries: int) -> None:
        """Raises a ValueError unless `n_entries` is one per environment (any number before the first chunk)."""
        if self._histories and n_entries != len(self._histories):
            raise ValueError(
                f"Expected {len(self._histories)} energies (one per environment), got {n_entries}."
            )

    def append(self, entries: Sequence[Any]) -> None:
        """Adds one chunk's entry to each environment's history (`check` first)."""
        self.check(len(entries))
        if not self._histories:
            self._histories = [[] for _ in entries]
        for history, entry in zip(self._histories, entries, strict=True):
            history.append(entry)

    def reset(self) -> None:
        self._histories = []
