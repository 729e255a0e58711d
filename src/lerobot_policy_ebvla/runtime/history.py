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


class ReadoutMonitor:
    """The one shape of the run-time monitors: `from_pretrained(checkpoint)`, then `update(policy.last_energy)`
    after each step, `reset()` with the policy.

    `update` counts each readout once (a readout it has seen returns its decisions again), so that it may be
    called after every `select_action` although the policy refines a chunk only every `n_action_steps` steps.
    A subclass decides on each new chunk (`_add`).
    """

    def __init__(self):
        self._histories = EnvironmentHistories()
        self._last: tuple[Any, list] | None = None

    def _add(self, readout) -> list:
        """Adds the readout's chunk to each environment's history; one decision per environment."""
        raise NotImplementedError

    def update(self, readout) -> list:
        """Adds one chunk per environment (the policy's `EnergyReadout`, (B,) entries) and answers for each.

        Raises:
            ValueError: Not one entry per environment, or the readout's chunk index is not the monitor's next
                (the policy and the monitor were not reset together).
        """
        if self._last is not None and self._last[0] is readout:
            return self._last[1]
        index, expected = readout.chunk_index, self._histories.n_chunks
        indices = index.reshape(-1).tolist() if hasattr(index, "reshape") else [index]
        if any(int(i) != expected for i in indices):
            raise ValueError(
                f"The readout is of chunk {index} of its episode, and this monitor has seen {expected} chunks: "
                "call `monitor.reset()` whenever the policy is reset (`policy.reset()`)."
            )
        decisions = self._add(readout)
        self._last = (readout, decisions)
        return decisions

    def reset(self) -> None:
        """Forgets the histories; call it when the environments reset (with `policy.reset()`)."""
        self._histories.reset()
        self._last = None
